/* The public load entry points and accessors. Every load runs pc_load_impl: scan the
 * graph (graph.c), plan (plan.c), then the checks that need a built model: rows must be
 * independent, and the metadata the pose checks of pc_run use. */
/* open, fstat and fdopen are POSIX, not C99: asked for before any header, where there is
 * POSIX; elsewhere pc_load_file opens with fopen alone. */
#if (defined(__unix__) || defined(__APPLE__)) && !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 200112L
#endif
#include "graph.h"
#include "load.h"
#include "plan.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#if defined(__unix__) || defined(__APPLE__)
#include <errno.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#define PC_POSIX_OPEN 1
#endif


/* ---- load-time checks ------------------------------------------------------------- */

/* Close enough for results of the same arithmetic in a different plan. Equal infinities
 * are the same result (their difference is NaN): a model answering a probe with infinity
 * is pc_run's output check to refuse, not a graph that mixes rows. */
static int pc_same_result(float a, float b)
{
    const float d = a > b ? a - b : b - a, s = a < 0 ? -a : a;
    return a == b || (a != a && b != b) || d <= 1e-5f * (s > 1.0f ? s : 1.0f);
}

static pc_status pc_forget_probe(pc_model *m)
{
    m->message[0] = '\0';
    return PC_OK;
}

/* pc_run splits a batch into chunks, so row i of the result must not depend on row j:
 * every pose of a batch plan must give what it gives alone. Checked on probe poses
 * (a reduction, reshape or gather across the batch axis fails it). */
PC_NOINLINE static pc_status pc_check_rows(pc_model *m, pc_error *err)
{
    float in[PC_PLAN_STRIDE * PC_POSE_WIDTH], out[PC_PLAN_STRIDE * PC_POSE_WIDTH];
    float t[PC_PLAN_STRIDE];
    const pc_plan *one = &m->plans[0], *batch;
    uint32_t seed = 12345u;
    size_t i, r, c;
    if (m->n_plans < 2)
        return PC_OK;
    batch = &m->plans[1];
    for (r = 0; r < batch->batch; r++) {
        float *p = in + r * PC_POSE_WIDTH, n2 = 0.0f;
        for (c = 0; c < PC_POSE_WIDTH; c++) {
            seed = seed * 1664525u + 1013904223u;
            p[c] = (float)(seed >> 8) / 8388608.0f - 1.0f; /* [-1, 1) */
            if (c >= 3)
                n2 += p[c] * p[c];
        }
        for (c = 3; c < PC_POSE_WIDTH; c++)
            p[c] /= sqrtf(n2);
    }
    for (r = 0; r < batch->batch; r++) { /* times: [0, 2 h) s */
        seed = seed * 1664525u + 1013904223u;
        t[r] = (float)(seed >> 8) / 8388608.0f * 3600.0f;
    }
    /* A probe the model cannot run says nothing about rows: pc_run will report it. */
    memcpy(batch->in, in, batch->batch * PC_POSE_WIDTH * sizeof(float));
    if (batch->t)
        memcpy(batch->t, t, batch->batch * sizeof(float));
    if (pc_run_steps(m, batch) != PC_OK)
        return pc_forget_probe(m);
    memcpy(out, batch->out, batch->batch * PC_POSE_WIDTH * sizeof(float));
    for (r = 0; r < batch->batch; r++) {
        memcpy(one->in, in + r * PC_POSE_WIDTH, sizeof(float) * PC_POSE_WIDTH);
        if (one->t)
            one->t[0] = t[r];
        if (pc_run_steps(m, one) != PC_OK)
            return pc_forget_probe(m);
        for (i = 0; i < PC_POSE_WIDTH; i++)
            if (!pc_same_result(one->out[i], out[r * PC_POSE_WIDTH + i]))
                return pc_fail(err, PC_ERR_GRAPH,
                               "graph mixes rows: pose %zu of a %zu-pose batch gives another "
                               "result than alone (column %zu); pc_run needs rows that are "
                               "independent (no reduction, reshape or gather across the batch "
                               "axis)", r, batch->batch, i);
    }
    return PC_OK;
}

/* Where a metadata value's bytes [s, end) are read: a NUL byte past the end. */
#define PC_AT (s < end ? *s : '\0')
#define PC_JSON_DEPTH 32

/* s past JSON's white space (its four bytes). */
static const char *pc_json_skip(const char *s, const char *end)
{
    while (PC_AT == ' ' || PC_AT == '\t' || PC_AT == '\n' || PC_AT == '\r')
        s++;
    return s;
}

/* A JSON number at s, into *x: the first byte after it, or NULL where none starts at s. */
static const char *pc_json_number(const char *s, const char *end, double *x)
{
    double v = 0.0, scale = 1.0;
    int negative = 0, e = 0, esign = 1;
    if (PC_AT == '-') {
        negative = 1;
        s++;
    }
    if (PC_AT == '0')
        s++;
    else if (PC_AT >= '1' && PC_AT <= '9')
        for (; PC_AT >= '0' && PC_AT <= '9'; s++)
            v = 10.0 * v + (PC_AT - '0');
    else
        return NULL;
    if (PC_AT == '.') {
        s++;
        if (PC_AT < '0' || PC_AT > '9')
            return NULL;
        for (; PC_AT >= '0' && PC_AT <= '9'; s++)
            v += (PC_AT - '0') * (scale *= 0.1);
    }
    if (PC_AT == 'e' || PC_AT == 'E') {
        s++;
        if (PC_AT == '-' || PC_AT == '+')
            esign = *s++ == '-' ? -1 : 1;
        if (PC_AT < '0' || PC_AT > '9')
            return NULL;
        for (; PC_AT >= '0' && PC_AT <= '9'; s++)
            e = e < 400 ? 10 * e + (PC_AT - '0') : e; /* beyond: inf or 0 alike */
    }
    for (; e > 0; e--)
        v = esign > 0 ? v * 10.0 : v / 10.0;
    *x = negative ? -v : v;
    return s;
}

/* Numbers of a JSON array such as [[-1, -0.5, 0], [1, 0.5, 1.2]] in the bytes [s, end),
 * read where they lie (a value of any length; a NUL byte is no part of it), without strtod
 * (which may allocate on small C libraries). JSON's grammar, as Python's json.loads reads
 * it (checks.py reads the same values so): arrays nested at most PC_JSON_DEPTH deep, JSON
 * numbers (no '+', no '.5', no leading zero), JSON's four white-space bytes between
 * tokens. Returns the count, or -1 on anything else. */
static int pc_parse_numbers(const char *s, const char *end, double *v, int cap)
{
    int n = 0, depth = 0;
    for (;;) {
        /* a value: an array opening, or a number */
        s = pc_json_skip(s, end);
        if (PC_AT == '[') {
            if (++depth > PC_JSON_DEPTH)
                return -1;
            s = pc_json_skip(s + 1, end);
            if (PC_AT != ']')
                continue;
            s++;
            depth--;
        } else {
            double x;
            if (!(s = pc_json_number(s, end, &x)) || n == cap)
                return -1;
            v[n++] = x;
        }
        /* after a value: the end of the text, a comma, or the closing of arrays */
        for (;;) {
            s = pc_json_skip(s, end);
            if (depth == 0)
                return s == end ? n : -1;
            if (PC_AT == ',') {
                s++;
                break;
            }
            if (PC_AT != ']')
                return -1;
            s++;
            depth--;
        }
    }
}
#undef PC_JSON_DEPTH
#undef PC_AT

/* A metadata value of bounds: `count` lower then `count` upper numbers, each a finite
 * float32, none above its upper partner. A file whose bounds were edited into NaN,
 * infinity or an inverted box is refused here: pc_run would otherwise let every pose
 * through (or none). */
static pc_status pc_read_bounds(const pc_builder *b, const char *key, pb_slice value, int count,
                                const char *expected, float *lo, float *hi)
{
    const char *text = (const char *)value.data;
    double v[6];
    int k;
    if (pc_parse_numbers(text, text + value.size, v, 2 * count) != 2 * count)
        return pc_fail(b->err, PC_ERR_MALFORMED, "metadata %s is '%.*s', expected %s", key,
                       value.size < 60 ? (int)value.size : 60, text, expected);
    for (k = 0; k < count; k++) {
        /* beyond FLT_MAX the conversion to float would be undefined */
        if (!(fabs(v[k]) <= FLT_MAX && fabs(v[k + count]) <= FLT_MAX))
            return pc_fail(b->err, PC_ERR_MALFORMED, "metadata %s: a bound is not a finite "
                           "float32 in column %d (expected %s)", key, k, expected);
        lo[k] = (float)v[k];
        hi[k] = (float)v[k + count];
        if (!(lo[k] <= hi[k]))
            return pc_fail(b->err, PC_ERR_MALFORMED, "metadata %s: lower bound above upper "
                           "bound in column %d", key, k);
    }
    return PC_OK;
}

/* A reader of the whole file, for onnx_next_meta. */
static void pc_meta_start(const pc_builder *b, pb_reader *r)
{
    pb_slice whole;
    whole.data = b->file;
    whole.size = b->file_size;
    pb_init(r, b->file, whole);
}

/* correction_reach, "[metres, radians]": two finite float32 numbers, not negative; kept
 * as pc_run compares them (squared distance, cos^2 of half the angle; a reach of pi or
 * more allows any rotation). */
static pc_status pc_read_reach(const pc_builder *b, pb_slice value, pc_model *m)
{
    const char *text = (const char *)value.data;
    double v[2];
    if (pc_parse_numbers(text, text + value.size, v, 2) != 2 || !(v[0] >= 0.0 && v[0] <= FLT_MAX) ||
        !(v[1] >= 0.0 && v[1] <= FLT_MAX))
        return pc_fail(b->err, PC_ERR_MALFORMED, "metadata correction_reach is '%.*s', "
                       "expected [metres, radians]: two finite numbers, not negative",
                       value.size < 60 ? (int)value.size : 60, text);
    m->reach_pos2 = (float)v[0] * (float)v[0];
    m->reach_cos2 = v[1] >= 3.141592653589793 ? 0.0f
                                              : (float)(cos(0.5 * (float)v[1]) * cos(0.5 * (float)v[1]));
    return PC_OK;
}

/* The metadata a model's checks need (posecorr.h): the position box of the training data
 * (input_bounds), how far its corrections reach (correction_reach), and for a model that
 * takes time the span of the training times (time_bounds). A model without the box or
 * the reach loads only when the caller allows it (PC_LOAD_ALLOW_UNBOUNDED); its poses are
 * then compared with infinite bounds, the same code path. */
static pc_status pc_read_checks(const pc_builder *b, pc_model *m, unsigned flags)
{
    static const char *const keys[3] = {"input_bounds", "time_bounds", "correction_reach"};
    pb_reader r;
    pb_slice key, value, found[3] = {{NULL, 0}, {NULL, 0}, {NULL, 0}};
    int more, k;
    pc_status st;
    pc_meta_start(b, &r);
    while ((more = onnx_next_meta(b, &r, &key, &value)) == PB_FIELD)
        for (k = 0; k < 3; k++)
            if (pb_slice_eq(key, keys[k])) {
                /* onnx.checker refuses it too; pc_metadata_lookup would show the first */
                if (found[k].data)
                    return pc_fail(b->err, PC_ERR_MALFORMED, "metadata %s appears twice",
                                   keys[k]);
                found[k] = value;
            }
    if (more == PB_ERROR)
        return r.status;
    for (k = 0; k < 3; k += 2) /* input_bounds, correction_reach */
        if (!found[k].data && !(flags & PC_LOAD_ALLOW_UNBOUNDED))
            return pc_fail(b->err, PC_ERR_CONTRACT, "no metadata %s: the model does not say %s "
                           "(to run it anyway, load with PC_LOAD_ALLOW_UNBOUNDED, on the "
                           "command line --allow-unbounded)", keys[k], k == 0 ?
                           "which positions it was fitted on" : "how far its corrections reach");
    for (k = 0; k < 3; k++) {
        m->lo[k] = -INFINITY;
        m->hi[k] = INFINITY;
    }
    m->reach_pos2 = INFINITY;
    m->reach_cos2 = 0.0f;
    if (found[0].data && (st = pc_read_bounds(b, keys[0], found[0], 3, "[[x_lo, y_lo, z_lo], "
                                              "[x_hi, y_hi, z_hi]] in metres", m->lo,
                                              m->hi)) != PC_OK)
        return st;
    if (found[1].data) {
        if ((st = pc_read_bounds(b, keys[1], found[1], 1, "[t_lo, t_hi] in seconds", &m->t_lo,
                                 &m->t_hi)) != PC_OK)
            return st;
        m->has_span = m->takes_time; /* a model without the input t ignores time */
    }
    if (found[2].data && (st = pc_read_reach(b, found[2], m)) != PC_OK)
        return st;
    m->bounded = found[0].data && m->reach_pos2 < INFINITY;
    return PC_OK;
}

/* The digest (docs/design.md, "Integrity"): metadata "model_digest" = "crc32c:" and eight
 * lowercase hexadecimal digits, the CRC-32C of the file's bytes with those eight digits
 * read as "00000000". Checked before anything else of the file is believed; a file
 * without it loads only with PC_LOAD_ALLOW_UNSIGNED. */
static pc_status pc_check_digest(const pc_builder *b, unsigned flags)
{
    static const char zeros[8] = {'0', '0', '0', '0', '0', '0', '0', '0'};
    pb_reader r;
    pb_slice key, value, digest = {NULL, 0};
    uint32_t stored = 0, crc;
    size_t at, i;
    int more;
    pc_meta_start(b, &r);
    while ((more = onnx_next_meta(b, &r, &key, &value)) == PB_FIELD)
        if (pb_slice_eq(key, "model_digest")) {
            if (digest.data)
                return pc_fail(b->err, PC_ERR_INTEGRITY, "metadata model_digest appears twice");
            digest = value;
        }
    if (more == PB_ERROR) /* the scan reports where the file is broken */
        return PC_OK;
    if (!digest.data)
        return flags & PC_LOAD_ALLOW_UNSIGNED
                   ? PC_OK
                   : pc_fail(b->err, PC_ERR_INTEGRITY, "no metadata model_digest: the file "
                             "carries no digest of its bytes (to run it anyway, load with "
                             "PC_LOAD_ALLOW_UNSIGNED, on the command line --allow-unsigned)");
    for (i = 0; i < digest.size && i < 15; i++) {
        const char ch = (char)digest.data[i];
        const int v = ch >= '0' && ch <= '9' ? ch - '0' : ch >= 'a' && ch <= 'f' ? ch - 'a' + 10 : -1;
        if (i < 7 ? ch != "crc32c:"[i] : v < 0)
            break;
        if (i >= 7)
            stored = stored << 4 | (uint32_t)v;
    }
    if (i != 15 || digest.size != 15)
        return pc_fail(b->err, PC_ERR_INTEGRITY, "metadata model_digest is '%.*s', expected "
                       "crc32c: and 8 lowercase hexadecimal digits",
                       (int)(digest.size < 40 ? digest.size : 40), (const char *)digest.data);
    at = (size_t)(digest.data - b->file) + 7;
    crc = pc_crc32c(0, b->file, at);
    crc = pc_crc32c(crc, zeros, sizeof zeros);
    crc = pc_crc32c(crc, b->file + at + 8, b->file_size - at - 8);
    if (crc != stored) {
        char got[9];
        for (i = 0; i < 8; i++)
            got[i] = "0123456789abcdef"[crc >> (28 - 4 * i) & 15u];
        got[8] = '\0';
        return pc_fail(b->err, PC_ERR_INTEGRITY, "the file's bytes give crc32c:%s where its "
                       "metadata model_digest says %.15s: the model was changed or damaged "
                       "after export", got, (const char *)digest.data);
    }
    return PC_OK;
}

/* ---- loading ---------------------------------------------------------------------- */

/* Every PC_LOAD_* flag of posecorr.h. */
#define PC_LOAD_FLAGS                                                                          \
    ((unsigned)(PC_LOAD_IN_PLACE | PC_LOAD_NO_PROGRAMS | PC_LOAD_NO_METADATA |                 \
                PC_LOAD_INTERPRET | PC_LOAD_ALLOW_UNBOUNDED | PC_LOAD_ALLOW_UNSIGNED))

pc_status pc_load_impl(const void *data, size_t size, const pc_options *opts, int any_io,
                       void *buf, size_t buf_size, pc_model **model, size_t *scratch_used,
                       pc_error *err)
{
    pc_builder b;
    pc_error local;
    pc_status st;
    const unsigned flags = opts ? opts->flags : 0u;
    if (!err)
        err = &local;
    err->status = PC_OK;
    err->message[0] = '\0';
    if (!model)
        return pc_fail(err, PC_ERR_ARGUMENT, "model pointer is NULL");
    *model = NULL;
    if (!data && size)
        return pc_fail(err, PC_ERR_ARGUMENT, "data is NULL");
    /* a flag of a newer header, given to this library, would be ignored without a word */
    if (flags & ~PC_LOAD_FLAGS)
        return pc_fail(err, PC_ERR_ARGUMENT, "options.flags holds bits 0x%x that no PC_LOAD_* "
                       "flag of this library names", flags & ~PC_LOAD_FLAGS);
    if (size == 0)
        return pc_fail(err, PC_ERR_TRUNCATED, "truncated file at byte 0 (empty)");
    memset(&b, 0, sizeof b);
    b.err = err;
    b.file = (const uint8_t *)data;
    b.file_size = size;
    b.any_io = any_io;
    b.cpu_avx2 = -1;
    b.in_place = opts && (opts->flags & PC_LOAD_IN_PLACE);
    if (buf)
        pc_scratch_use_buffer(&b.scratch, buf, buf_size);
    st = any_io ? PC_OK : pc_check_digest(&b, flags);
    if (st == PC_OK)
        st = pc_scan_graph(&b);
    if (st == PC_OK)
        st = pc_plan_build(&b, opts, buf, buf_size, model);
    if (st == PC_OK && !any_io && (st = pc_read_checks(&b, *model, flags)) != PC_OK) {
        pc_free(*model);
        *model = NULL;
    }
    if (st == PC_ERR_MEMORY && buf && err->status == PC_ERR_MEMORY)
        pc_fail(err, st, "the %zu-byte buffer is too small for this model (pc_required_bytes)",
                buf_size);
    /* Scratch alone before the arena is placed, scratch beside the arena after. */
    if (scratch_used && st == PC_OK)
        *scratch_used = b.peak_unplaced > b.scratch.peak + (*model)->arena_bytes
                            ? b.peak_unplaced - (*model)->arena_bytes
                            : b.scratch.peak;
    pc_scratch_release(&b.scratch);
    if (st == PC_OK && !any_io && (st = pc_check_rows(*model, err)) != PC_OK) {
        pc_free(*model);
        *model = NULL;
    }
    if (st != PC_OK && err->status == PC_OK)
        pc_fail(err, st, "%s", pc_status_name(st));
    return st;
}

pc_status pc_load_memory(const void *data, size_t size, const pc_options *opts,
                         pc_model **model, pc_error *err)
{
    return pc_load_impl(data, size, opts, 0, NULL, 0, model, NULL, err);
}

pc_status pc_required_bytes(const void *data, size_t size, const pc_options *opts,
                            size_t *bytes, pc_error *err)
{
    pc_model *m;
    size_t scratch;
    pc_status st;
    if (!bytes)
        return pc_fail(err, PC_ERR_ARGUMENT, "bytes pointer is NULL");
    *bytes = 0;
    st = pc_load_impl(data, size, opts, 0, NULL, 0, &m, &scratch, err);
    if (st != PC_OK)
        return st;
    /* Scratch from the aligned start, the arena aligned down at the end. */
    *bytes = PC_ALIGN + scratch + m->arena_bytes + PC_ALIGN;
    pc_free(m);
    return PC_OK;
}

pc_status pc_load_into(const void *data, size_t size, const pc_options *opts, void *buffer,
                       size_t buffer_size, pc_model **model, pc_error *err)
{
    if (!buffer) {
        if (model)
            *model = NULL;
        return pc_fail(err, PC_ERR_ARGUMENT, "buffer is NULL");
    }
    return pc_load_impl(data, size, opts, 0, buffer, buffer_size, model, NULL, err);
}

#ifdef PC_POSIX_OPEN
static const char *pc_file_kind(mode_t mode)
{
    return S_ISDIR(mode) ? "a folder" : S_ISFIFO(mode) ? "a FIFO" : S_ISCHR(mode) ? "a character device"
         : S_ISBLK(mode) ? "a block device" : S_ISSOCK(mode) ? "a socket" : "a special file";
}
#endif

#ifdef PC_POSIX_OPEN
/* Why open(2) failed, in the words of strerror on glibc, without strerror (whose buffer
 * another thread's call may share). */
static const char *pc_open_cause(int e)
{
    switch (e) {
    case ENOENT: return ": No such file or directory";
    case EACCES: return ": Permission denied";
    case ENOTDIR: return ": Not a directory";
    case ELOOP: return ": Too many levels of symbolic links";
    case ENAMETOOLONG: return ": File name too long";
    case EMFILE: return ": Too many open files";
    case ENFILE: return ": Too many open files in system";
    default: return "";
    }
}
#endif

/* fopen of a FIFO waits for a writer, forever, and a device reads without end: where there
 * is POSIX the file is opened without waiting (O_NONBLOCK) and refused at once unless fstat
 * says it is a regular file - the file opened, not one a stat before the open saw. */
static pc_status pc_open_regular(const char *path, FILE **fp, pc_error *err)
{
#ifdef PC_POSIX_OPEN
    struct stat st;
    int flags;
    const int fd = open(path, O_RDONLY | O_NONBLOCK);
    *fp = NULL;
    if (fd < 0)
        return pc_fail(err, PC_ERR_IO, "cannot open '%s'%s", path, pc_open_cause(errno));
    if (fstat(fd, &st) != 0) {
        close(fd);
        return pc_fail(err, PC_ERR_IO, "cannot read '%s'", path);
    }
    if (!S_ISREG(st.st_mode)) {
        close(fd);
        return pc_fail(err, PC_ERR_IO, "cannot read '%s': is %s, expected a regular file", path,
                       pc_file_kind(st.st_mode));
    }
    flags = fcntl(fd, F_GETFL);
    if (flags == -1 || fcntl(fd, F_SETFL, flags & ~O_NONBLOCK) == -1 || !(*fp = fdopen(fd, "rb"))) {
        close(fd);
        return pc_fail(err, PC_ERR_IO, "cannot open '%s'", path);
    }
    return PC_OK;
#else
    *fp = fopen(path, "rb");
    return *fp ? PC_OK : pc_fail(err, PC_ERR_IO, "cannot open '%s'", path);
#endif
}

pc_status pc_load_file(const char *path, const pc_options *opts, pc_model **model,
                       pc_error *err)
{
    FILE *fp;
    long len;
    uint8_t *buf;
    pc_status st;
    pc_error local;
    pc_options copied;
    if (!err)
        err = &local;
    if (model)
        *model = NULL;
    if (!path || !model)
        return pc_fail(err, PC_ERR_ARGUMENT, "path or model pointer is NULL");
    st = pc_open_regular(path, &fp, err);
    if (st != PC_OK)
        return st;
    if (fseek(fp, 0, SEEK_END) != 0 || (len = ftell(fp)) < 0 || fseek(fp, 0, SEEK_SET) != 0) {
        fclose(fp);
        return pc_fail(err, PC_ERR_IO, "cannot determine the size of '%s'", path);
    }
    /* A folder opens and seeks on some C libraries, its size reading as LONG_MAX: one byte
     * read first makes it "cannot read", not "out of memory". */
    if ((getc(fp) == EOF && ferror(fp)) || fseek(fp, 0, SEEK_SET) != 0) {
        fclose(fp);
        return pc_fail(err, PC_ERR_IO, "cannot read '%s': not a regular file (a folder?)", path);
    }
    buf = (uint8_t *)malloc(len > 0 ? (size_t)len : 1);
    if (!buf) {
        fclose(fp);
        return pc_fail(err, PC_ERR_MEMORY, "out of memory reading '%s'", path);
    }
    if (len > 0 && fread(buf, 1, (size_t)len, fp) != (size_t)len) {
        fclose(fp);
        free(buf);
        return pc_fail(err, PC_ERR_IO, "cannot read '%s'", path);
    }
    /* /proc's files say 0 bytes and hold more: read as they say, they were "empty". */
    if (getc(fp) != EOF) {
        fclose(fp);
        free(buf);
        return pc_fail(err, PC_ERR_IO, "cannot read '%s': it holds more than the %lu bytes its "
                       "size says (a file that changes, or one the system generates)", path,
                       (unsigned long)len);
    }
    fclose(fp);
    /* The bytes are freed on return: a model in place would read them after that. */
    if (opts && (opts->flags & PC_LOAD_IN_PLACE)) {
        copied = *opts;
        copied.flags &= ~(unsigned)PC_LOAD_IN_PLACE;
        opts = &copied;
    }
    st = pc_load_memory(buf, (size_t)len, opts, model, err);
    free(buf);
    return st;
}

void pc_free(pc_model *model)
{
    if (model && model->owns_arena)
        free(model);
}

/* ---- accessors -------------------------------------------------------------------- */

int pc_version(void)
{
    return PC_VERSION_NUMBER;
}

size_t pc_metadata_count(const pc_model *model)
{
    return model ? model->n_meta : 0;
}

const char *pc_metadata_key(const pc_model *model, size_t index)
{
    return model && index < model->n_meta ? model->meta_key[index] : NULL;
}

const char *pc_metadata_value(const pc_model *model, size_t index)
{
    return model && index < model->n_meta ? model->meta_value[index] : NULL;
}

const char *pc_metadata_lookup(const pc_model *model, const char *key)
{
    size_t i;
    if (!model || !key)
        return NULL;
    for (i = 0; i < model->n_meta; i++)
        if (strcmp(model->meta_key[i], key) == 0)
            return model->meta_value[i];
    return NULL;
}

size_t pc_max_batch(const pc_model *model) { return model ? model->max_batch : 0; }
size_t pc_arena_bytes(const pc_model *model) { return model ? model->arena_bytes : 0; }
size_t pc_step_count(const pc_model *model)
{
    return model && model->n_plans ? model->plans[0].n_steps : 0;
}
size_t pc_node_count(const pc_model *model) { return model ? model->n_nodes : 0; }
const char *pc_model_message(const pc_model *model) { return model ? model->message : ""; }

int pc_model_takes_time(const pc_model *model) { return model ? model->takes_time : 0; }

/* ---- the path each step of the one-pose plan runs ---------------------------------------- */

static const char *const pc_path_names[PC_PATH_COUNT] = {"specialised", "general", "interpreted"};

const char *pc_path_name(pc_path path)
{
    return (unsigned)path < PC_PATH_COUNT ? pc_path_names[path] : "unknown";
}

/* A chain is specialised when every layer runs the kernel of its K and N. */
static pc_path pc_chain_path(const pc_gemm_chain *q, char *why, size_t size)
{
    char sizes[96];
    const char *first = "";
    size_t i, at = 0, len;
    pc_format(sizes, sizeof sizes, "%zu", q->layer[0].g.K);
    for (i = 0; i < q->n_layers; i++) {
        const char *w = pc_chain_layer_why(&q->layer[i]);
        len = strlen(sizes);
        pc_format(sizes + len, sizeof sizes - len, "-%zu", q->layer[i].g.N);
        if (*w && !*first) {
            first = w;
            at = i;
        }
    }
    if (!*first) {
        pc_format(why, size, "dense chain %s: every layer runs the kernel of its K and N", sizes);
        return PC_PATH_SPECIALISED;
    }
    pc_format(why, size, "dense chain %s: layer %zu (%zu -> %zu) runs the general layer: %s",
              sizes, at, q->layer[at].g.K, q->layer[at].g.N, first);
    return PC_PATH_GENERAL;
}

static pc_path pc_program_path(const pc_step *s, char *why, size_t size)
{
#ifdef PC_NO_COMPILED_PROGRAMS
    const size_t n_compiled = 0;
#else
    const size_t n_compiled = pc_n_compiled_programs;
    size_t k;
#endif
    if (s->fn == k_scalar_program) {
        pc_format(why, size, "one-pose program of %zu operations with offsets wider than 16 bits",
                  ((const pc_scalar_program *)s->prm)->n_ops);
        return PC_PATH_INTERPRETED;
    }
    if (s->fn == k_scalar_program16) {
        pc_format(why, size, "one-pose program of %zu operations: %s",
                  ((const pc_scalar_program16 *)s->prm)->n_ops,
                  n_compiled ? "no compiled program has its shape, or PC_LOAD_INTERPRET"
                                         : "the library is built without compiled programs");
        return PC_PATH_INTERPRETED;
    }
#ifndef PC_NO_COMPILED_PROGRAMS
    for (k = 0; k < n_compiled; k++)
        if (s->fn == pc_compiled_programs[k].fn) {
            pc_format(why, size, "one-pose program compiled ahead of time (entry %zu of %zu)", k,
                      n_compiled);
            return PC_PATH_SPECIALISED;
        }
#endif
    if (s->fn == k_gemm || s->fn == k_matmul)
        pc_format(why, size, "Gemm or MatMul outside a chain (a chain takes a bias row, no "
                             "transposes, and tanh or no activation)");
    else
        pc_format(why, size, "a node's own kernel (no one-pose program or chain form)");
    return PC_PATH_GENERAL;
}

pc_status pc_model_step_path(const pc_model *model, size_t step, pc_path *path, char *why,
                             size_t why_size)
{
    char none[1];
    const pc_step *s;
    if (!model || !path || (!why && why_size) || step >= pc_step_count(model))
        return PC_ERR_ARGUMENT;
    if (!why_size) {
        why = none;
        why_size = sizeof none;
    }
    s = &model->plans[0].steps[step];
    *path = s->fn == k_gemm_chain ? pc_chain_path((const pc_gemm_chain *)s->prm, why, why_size)
                                  : pc_program_path(s, why, why_size);
    return PC_OK;
}
