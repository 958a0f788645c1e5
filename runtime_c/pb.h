/* Layer 1, protobuf wire format: fields of one message, no knowledge of ONNX. */
#ifndef PC_PB_H
#define PC_PB_H

#include "base.h"

/* A view into the loaded buffer; nothing is copied while parsing. */
typedef struct pb_slice {
    const uint8_t *data;
    size_t size;
} pb_slice;

enum { PB_VARINT = 0, PB_FIXED64 = 1, PB_BYTES = 2, PB_FIXED32 = 5 };

typedef struct pb_reader {
    const uint8_t *file;  /* start of the whole buffer, for byte offsets in messages */
    const uint8_t *pos;
    const uint8_t *end;
    pc_status status;     /* why pb_next returned PB_ERROR */
} pb_reader;

typedef struct pb_field {
    uint32_t number;
    uint32_t wire;
    uint64_t varint;   /* PB_VARINT, or the raw bits of PB_FIXED32 / PB_FIXED64 */
    pb_slice bytes;    /* PB_BYTES */
    size_t offset;     /* byte offset of the tag in the file */
} pb_field;

/* pb_next's three outcomes, so that one loop reads a message:
 *     while ((k = pb_next(&r, &f, err)) == PB_FIELD) { ... }
 *     if (k == PB_ERROR) return r.status;                                          */
enum { PB_ERROR = -1, PB_END = 0, PB_FIELD = 1 };

void pb_init(pb_reader *r, const uint8_t *file, pb_slice msg);
int pb_next(pb_reader *r, pb_field *f, pc_error *err);
pc_status pb_read_varint(pb_reader *r, uint64_t *v, pc_error *err);
int pb_slice_eq(pb_slice s, const char *z);
int pb_slice_same(pb_slice a, pb_slice b);
float pb_bits_to_float(uint32_t bits);

/* Repeated scalar fields may be packed (one PB_BYTES field) or not (one field per
 * element); these count and decode both forms from a field already read. */
pc_status pb_count_packed(const uint8_t *file, const pb_field *f, uint32_t elem_wire,
                          size_t *count, pc_error *err);
pc_status pb_decode_repeated(const uint8_t *file, const pb_field *f, uint32_t elem_wire,
                             int64_t *ints, float *floats, size_t cap, size_t *n,
                             pc_error *err);

#endif
