/* Protobuf wire-format reader for the subset of ONNX that posecorr uses.
 *
 * The reader never copies: strings, bytes and sub-messages come back as slices of the
 * caller's buffer. Every length is checked against the end of the enclosing message
 * before it is used, so a hostile file can at worst produce an error status. */
#include "pb.h"

#include <string.h>

void pb_init(pb_reader *r, const uint8_t *file, pb_slice msg)
{
    r->file = file;
    r->pos = msg.data;
    r->end = msg.data + msg.size;
    r->status = PC_OK;
}

static size_t pb_offset(const pb_reader *r)
{
    return (size_t)(r->pos - r->file);
}

pc_status pb_read_varint(pb_reader *r, uint64_t *v, pc_error *err)
{
    uint64_t result = 0;
    unsigned shift = 0;
    const size_t start = pb_offset(r);
    while (r->pos < r->end) {
        const uint8_t byte = *r->pos++;
        if (shift == 63 && (byte & 0x7e))
            return pc_fail(err, PC_ERR_MALFORMED, "varint overflows 64 bits at byte %zu", start);
        result |= (uint64_t)(byte & 0x7f) << shift;
        if (!(byte & 0x80)) {
            *v = result;
            return PC_OK;
        }
        shift += 7;
        if (shift > 63)
            return pc_fail(err, PC_ERR_MALFORMED, "varint longer than 10 bytes at byte %zu", start);
    }
    return pc_fail(err, PC_ERR_TRUNCATED, "truncated file at byte %zu (inside a varint)", pb_offset(r));
}

static pc_status pb_read_fixed(pb_reader *r, size_t width, uint64_t *v, pc_error *err)
{
    uint64_t result = 0;
    size_t i;
    if ((size_t)(r->end - r->pos) < width)
        return pc_fail(err, PC_ERR_TRUNCATED, "truncated file at byte %zu (inside a %zu-byte field)",
                       pb_offset(r), width);
    /* Little-endian by definition of the wire format, whatever the host is. */
    for (i = 0; i < width; i++)
        result |= (uint64_t)r->pos[i] << (8 * i);
    r->pos += width;
    *v = result;
    return PC_OK;
}

static pc_status pb_read_field(pb_reader *r, pb_field *f, pc_error *err)
{
    uint64_t tag, len;
    pc_status st;
    f->offset = pb_offset(r);
    if ((st = pb_read_varint(r, &tag, err)) != PC_OK)
        return st;
    f->number = (uint32_t)(tag >> 3);
    f->wire = (uint32_t)(tag & 7);
    if ((tag >> 3) == 0 || (tag >> 3) > 0x1fffffff)
        return pc_fail(err, PC_ERR_MALFORMED, "invalid field number at byte %zu", f->offset);
    f->varint = 0;
    f->bytes.data = NULL;
    f->bytes.size = 0;
    switch (f->wire) {
    case PB_VARINT:
        return pb_read_varint(r, &f->varint, err);
    case PB_FIXED64:
        return pb_read_fixed(r, 8, &f->varint, err);
    case PB_FIXED32:
        return pb_read_fixed(r, 4, &f->varint, err);
    case PB_BYTES:
        if ((st = pb_read_varint(r, &len, err)) != PC_OK)
            return st;
        if (len > (uint64_t)(r->end - r->pos))
            return pc_fail(err, PC_ERR_TRUNCATED,
                           "truncated file at byte %zu (field %lu declares %llu bytes, %zu left)",
                           pb_offset(r), (unsigned long)f->number, (unsigned long long)len,
                           (size_t)(r->end - r->pos));
        f->bytes.data = r->pos;
        f->bytes.size = (size_t)len;
        r->pos += len;
        return PC_OK;
    default:
        /* Groups (3, 4) are not used by ONNX; anything else is not protobuf. */
        return pc_fail(err, PC_ERR_MALFORMED, "unsupported wire type %lu at byte %zu",
                       (unsigned long)f->wire, f->offset);
    }
}

int pb_next(pb_reader *r, pb_field *f, pc_error *err)
{
    if (r->pos >= r->end)
        return PB_END;
    r->status = pb_read_field(r, f, err);
    return r->status == PC_OK ? PB_FIELD : PB_ERROR;
}

int pb_slice_same(pb_slice a, pb_slice b)
{
    return a.size == b.size && (a.size == 0 || memcmp(a.data, b.data, a.size) == 0);
}

int pb_slice_eq(pb_slice s, const char *z)
{
    const size_t n = strlen(z);
    return s.size == n && (n == 0 || memcmp(s.data, z, n) == 0);
}

float pb_bits_to_float(uint32_t bits)
{
    float f;
    memcpy(&f, &bits, sizeof f);
    return f;
}

static size_t pb_wire_width(uint32_t wire)
{
    return wire == PB_FIXED32 ? 4 : wire == PB_FIXED64 ? 8 : 0;
}

pc_status pb_count_packed(const uint8_t *file, const pb_field *f, uint32_t elem_wire,
                          size_t *count, pc_error *err)
{
    pb_reader r;
    uint64_t v;
    pc_status st;
    size_t n = 0;
    if (f->wire == elem_wire) {
        *count = 1;
        return PC_OK;
    }
    if (f->wire != PB_BYTES)
        return pc_fail(err, PC_ERR_MALFORMED, "field %lu at byte %zu has wire type %lu",
                       (unsigned long)f->number, f->offset, (unsigned long)f->wire);
    if (elem_wire != PB_VARINT) {
        const size_t w = pb_wire_width(elem_wire);
        if (f->bytes.size % w)
            return pc_fail(err, PC_ERR_MALFORMED,
                           "packed field %lu at byte %zu is not a multiple of %zu bytes",
                           (unsigned long)f->number, f->offset, w);
        *count = f->bytes.size / w;
        return PC_OK;
    }
    pb_init(&r, file, f->bytes);
    while (r.pos < r.end) {
        if ((st = pb_read_varint(&r, &v, err)) != PC_OK)
            return st;
        n++;
    }
    *count = n;
    return PC_OK;
}

pc_status pb_decode_repeated(const uint8_t *file, const pb_field *f, uint32_t elem_wire,
                             int64_t *ints, float *floats, size_t cap, size_t *n,
                             pc_error *err)
{
    pb_reader r;
    uint64_t v;
    pc_status st;
    if (f->wire == elem_wire) {
        if (*n >= cap)
            return pc_fail(err, PC_ERR_MALFORMED, "too many elements in field %lu at byte %zu",
                           (unsigned long)f->number, f->offset);
        if (ints)
            ints[*n] = (int64_t)f->varint;
        if (floats)
            floats[*n] = pb_bits_to_float((uint32_t)f->varint);
        (*n)++;
        return PC_OK;
    }
    if (f->wire != PB_BYTES)
        return pc_fail(err, PC_ERR_MALFORMED, "field %lu at byte %zu has wire type %lu",
                       (unsigned long)f->number, f->offset, (unsigned long)f->wire);
    pb_init(&r, file, f->bytes);
    while (r.pos < r.end) {
        if (elem_wire == PB_VARINT)
            st = pb_read_varint(&r, &v, err);
        else
            st = pb_read_fixed(&r, pb_wire_width(elem_wire), &v, err);
        if (st != PC_OK)
            return st;
        if (*n >= cap)
            return pc_fail(err, PC_ERR_MALFORMED, "too many elements in field %lu at byte %zu",
                           (unsigned long)f->number, f->offset);
        if (ints)
            ints[*n] = (int64_t)v;
        if (floats)
            floats[*n] = pb_bits_to_float((uint32_t)v);
        (*n)++;
    }
    return PC_OK;
}
