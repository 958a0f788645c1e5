/* C unit tests: protobuf reader, status table, tanh accuracy against libm, loader error
 * paths and pc_run contract on models built here with a minimal protobuf writer.
 * Operator semantics are checked against onnxruntime by the pytest parity suite. */
#include "base.h"
#include "kernels.h"
#include "pb.h"

#include <limits.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int n_pass = 0, n_fail = 0;

#define CHECK(cond)                                                                        \
    do {                                                                                   \
        if (cond)                                                                          \
            n_pass++;                                                                      \
        else {                                                                             \
            n_fail++;                                                                      \
            fprintf(stderr, "FAIL %s:%d: %s\n", __FILE__, __LINE__, #cond);               \
        }                                                                                  \
    } while (0)

/* ---- a minimal protobuf writer ---------------------------------------------------- */

typedef struct buf {
    uint8_t d[16384];
    size_t n;
} buf;

static void put_varint(buf *b, uint64_t v)
{
    do {
        uint8_t byte = v & 0x7f;
        v >>= 7;
        b->d[b->n++] = byte | (v ? 0x80 : 0);
    } while (v);
}
static void put_tag(buf *b, unsigned field, unsigned wire) { put_varint(b, (uint64_t)field << 3 | wire); }
static void put_int(buf *b, unsigned field, uint64_t v) { put_tag(b, field, 0); put_varint(b, v); }
static void put_bytes(buf *b, unsigned field, const void *p, size_t n)
{
    put_tag(b, field, 2);
    put_varint(b, n);
    memcpy(b->d + b->n, p, n);
    b->n += n;
}
static void put_str(buf *b, unsigned field, const char *s) { put_bytes(b, field, s, strlen(s)); }
/* The float sum a model computes: C may evaluate the test's own sum wider (FLT_EVAL_METHOD 1
 * on s390x, 2 on x87) and compare it unrounded; the call rounds it as the runtime stores it. */
static float f32(float x) { return x; }
/* A float as the wire format and raw_data hold it: little-endian, whatever the host. */
static void put_f32le(buf *b, float x)
{
    uint32_t u;
    int i;
    memcpy(&u, &x, 4);
    for (i = 0; i < 4; i++)
        b->d[b->n++] = (uint8_t)(u >> (8 * i));
}
static void put_msg(buf *b, unsigned field, const buf *m) { put_bytes(b, field, m->d, m->n); }

static void value_info(buf *out, unsigned field, const char *name, int width, int elem)
{
    buf vi = {{0}, 0}, type = {{0}, 0}, tt = {{0}, 0}, shape = {{0}, 0}, d0 = {{0}, 0}, d1 = {{0}, 0};
    put_str(&d0, 2, "N");
    put_int(&d1, 1, (uint64_t)width);
    put_msg(&shape, 1, &d0);
    put_msg(&shape, 1, &d1);
    put_int(&tt, 1, (uint64_t)elem);
    put_msg(&tt, 2, &shape);
    put_msg(&type, 1, &tt);
    put_str(&vi, 1, name);
    put_msg(&vi, 2, &type);
    put_msg(out, field, &vi);
}

typedef struct spec {
    const char *in_name;
    int in_width;
    const char *op;         /* node: op(pose, c) -> corrected, or op(pose) if !with_const */
    int with_const;
    int raw;                /* initializer as raw_data (1) or float_data (0) */
    const char *node_input; /* overrides the second input name */
    int self_loop;          /* node consumes its own output */
} spec;

static size_t model_without_meta;

static void build(buf *model, const spec *s, const float *c)
{
    buf graph = {{0}, 0}, node = {{0}, 0}, tensor = {{0}, 0}, opset = {{0}, 0}, meta = {{0}, 0};
    int k;
    put_str(&node, 1, s->self_loop ? "corrected" : "pose");
    if (s->with_const)
        put_str(&node, 1, s->node_input ? s->node_input : "c");
    put_str(&node, 2, "corrected");
    put_str(&node, 3, "node0");
    put_str(&node, 4, s->op);
    put_msg(&graph, 1, &node);
    put_str(&graph, 2, "g");
    if (s->with_const) {
        put_int(&tensor, 1, 7);
        put_int(&tensor, 2, 1);
        put_str(&tensor, 8, "c");
        put_tag(&tensor, s->raw ? 9 : 4, 2); /* raw_data, or packed float_data */
        put_varint(&tensor, 7 * 4);
        for (k = 0; k < 7; k++)
            put_f32le(&tensor, c[k]);
        put_msg(&graph, 5, &tensor);
    }
    value_info(&graph, 11, s->in_name, s->in_width, 1);
    value_info(&graph, 12, "corrected", 7, 1);
    model->n = 0;
    put_int(model, 1, 8);
    put_str(&opset, 1, "");
    put_int(&opset, 2, 17);
    put_msg(model, 8, &opset);
    put_msg(model, 7, &graph);
    model_without_meta = model->n;
    put_str(&meta, 1, "method");
    put_str(&meta, 2, "pmc");
    put_msg(model, 14, &meta);
}

static const spec ADD = {"pose", 7, "Add", 1, 1, NULL, 0};
/* The models built here carry neither bounds nor a digest: loaded as another producer's. */
static const pc_options ALLOW = {0, PC_LOAD_ALLOW_UNBOUNDED | PC_LOAD_ALLOW_UNSIGNED, 0};

/* n poses: positions from a fixed pattern in [-0.5, 0.5], unit quaternions */
static void fill_poses(float *in, size_t n)
{
    size_t i, c;
    for (i = 0; i < n; i++) {
        float *p = in + i * 7, n2 = 0.0f;
        for (c = 0; c < 7; c++) {
            p[c] = (float)(((i * 7 + c) * 37) % 101) * 0.01f - 0.5f;
            if (c >= 3)
                n2 += p[c] * p[c];
        }
        if (n2 == 0.0f) {
            p[3] = 1.0f;
            n2 = 1.0f;
        }
        for (c = 3; c < 7; c++)
            p[c] /= sqrtf(n2);
    }
}

/* build, then one more metadata entry (key NULL: none). */
static void build_meta(buf *model, const spec *s, const float *c, const char *key,
                       const char *value)
{
    buf meta = {{0}, 0};
    build(model, s, c);
    if (!key)
        return;
    put_str(&meta, 1, key);
    put_str(&meta, 2, value);
    put_msg(model, 14, &meta);
}

/* ---- tests ------------------------------------------------------------------------ */

static void test_varint(void)
{
    const uint8_t one[] = {0x96, 0x01};
    const uint8_t ten[] = {0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x01};
    const uint8_t over[] = {0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x7f};
    const uint8_t trunc[] = {0x80, 0x80};
    pb_reader r;
    pb_slice s;
    uint64_t v = 0;
    pc_error err;
    s.data = one; s.size = sizeof one;
    pb_init(&r, one, s);
    CHECK(pb_read_varint(&r, &v, &err) == PC_OK && v == 150);
    s.data = ten; s.size = sizeof ten;
    pb_init(&r, ten, s);
    CHECK(pb_read_varint(&r, &v, &err) == PC_OK && v == UINT64_MAX);
    s.data = over; s.size = sizeof over;
    pb_init(&r, over, s);
    CHECK(pb_read_varint(&r, &v, &err) == PC_ERR_MALFORMED);
    s.data = trunc; s.size = sizeof trunc;
    pb_init(&r, trunc, s);
    CHECK(pb_read_varint(&r, &v, &err) == PC_ERR_TRUNCATED);
    CHECK(strstr(err.message, "byte 2") != NULL);
}

static void test_fields(void)
{
    buf b = {{0}, 0};
    pb_reader r;
    pb_field f;
    pb_slice s;
    pc_error err;
    float x = 1.5f;
    int64_t ints[8];
    size_t n = 0, count = 0;
    put_int(&b, 3, 300);
    put_tag(&b, 2, 5);
    put_f32le(&b, x);
    put_str(&b, 1, "abc");
    put_tag(&b, 8, 2); /* packed ints 1, 2, 300 */
    put_varint(&b, 4);
    put_varint(&b, 1);
    put_varint(&b, 2);
    put_varint(&b, 300);
    s.data = b.d; s.size = b.n;
    pb_init(&r, b.d, s);
    CHECK(pb_next(&r, &f, &err) == PB_FIELD && f.number == 3 && f.wire == PB_VARINT && f.varint == 300);
    CHECK(pb_next(&r, &f, &err) == PB_FIELD && f.wire == PB_FIXED32 && pb_bits_to_float((uint32_t)f.varint) == 1.5f);
    CHECK(pb_next(&r, &f, &err) == PB_FIELD && pb_slice_eq(f.bytes, "abc"));
    CHECK(pb_next(&r, &f, &err) == PB_FIELD && f.number == 8);
    CHECK(pb_count_packed(b.d, &f, PB_VARINT, &count, &err) == PC_OK && count == 3);
    CHECK(pb_decode_repeated(b.d, &f, PB_VARINT, ints, NULL, 8, &n, &err) == PC_OK && n == 3 && ints[2] == 300);
    n = 0;
    CHECK(pb_decode_repeated(b.d, &f, PB_VARINT, ints, NULL, 2, &n, &err) == PC_ERR_MALFORMED);
    CHECK(pb_next(&r, &f, &err) == PB_END);
    /* length beyond the end of the message */
    b.n = 0;
    put_tag(&b, 1, 2);
    put_varint(&b, 50);
    b.d[b.n++] = 'x';
    s.data = b.d; s.size = b.n;
    pb_init(&r, b.d, s);
    CHECK((pb_next(&r, &f, &err) == PB_ERROR && r.status == PC_ERR_TRUNCATED));
    /* wire types 3/4/6/7 and field number 0 */
    b.n = 0;
    put_tag(&b, 1, 3);
    s.data = b.d; s.size = b.n;
    pb_init(&r, b.d, s);
    CHECK((pb_next(&r, &f, &err) == PB_ERROR && r.status == PC_ERR_MALFORMED));
    b.n = 0;
    put_tag(&b, 0, 0);
    put_varint(&b, 1);
    s.data = b.d; s.size = b.n;
    pb_init(&r, b.d, s);
    CHECK((pb_next(&r, &f, &err) == PB_ERROR && r.status == PC_ERR_MALFORMED));
    /* truncated fixed32 */
    b.n = 0;
    put_tag(&b, 2, 5);
    b.d[b.n++] = 0;
    s.data = b.d; s.size = b.n;
    pb_init(&r, b.d, s);
    CHECK((pb_next(&r, &f, &err) == PB_ERROR && r.status == PC_ERR_TRUNCATED));
}

static void test_status_names(void)
{
    int i, j;
    for (i = 0; i < PC_STATUS_COUNT; i++) {
        CHECK(strcmp(pc_status_name((pc_status)i), "unknown status") != 0);
        for (j = 0; j < i; j++)
            CHECK(strcmp(pc_status_name((pc_status)i), pc_status_name((pc_status)j)) != 0);
    }
    CHECK(strcmp(pc_status_name(PC_STATUS_COUNT), "unknown status") == 0);
}

/* pc_format (the library's own formatter) against the host's snprintf on every
 * conversion of its subset, at the extremes of each width, and on truncation. */
static void test_format(void)
{
    char mine[64], libc[64];
    const char *name = "initializer";
#define SAME(...)                                                                          \
    do {                                                                                   \
        pc_format(mine, sizeof mine, __VA_ARGS__);                                         \
        snprintf(libc, sizeof libc, __VA_ARGS__);                                          \
        CHECK(strcmp(mine, libc) == 0);                                                    \
        if (strcmp(mine, libc))                                                            \
            fprintf(stderr, "  pc_format '%s', snprintf '%s'\n", mine, libc);              \
    } while (0)
    SAME("byte %zu of %zu, field %lu", (size_t)0, SIZE_MAX, 4294967295UL);
    SAME("%d %d %d %i", 0, -1, INT_MIN, INT_MAX);
    SAME("%u %x %lu %ld", UINT_MAX, 0xbeefu, ULONG_MAX, LONG_MIN);
    SAME("%lld %lld %llu", LLONG_MIN, LLONG_MAX, ULLONG_MAX);
    SAME("'%.*s' '%.3s' '%s' %c 100%%", 4, name, name, name, 'x');
    SAME("%.*s|%.0s|", 0, name, name);
    /* truncation: as snprintf, at most size - 1 characters and a terminator */
    pc_format(mine, 8, "pose %zu of %s", (size_t)123456, name);
    CHECK(strcmp(mine, "pose 12") == 0);
    mine[0] = 'z';
    pc_format(mine, 1, "%s", name);
    CHECK(mine[0] == '\0');
#undef SAME
}

static void test_tanh(void)
{
    double worst = 0.0, at = 0.0;
    long i;
    for (i = -1200000; i <= 1200000; i++) {
        const float x = (float)i * 1e-5f;
        const double e = fabs((double)pc_tanh(x) - tanh((double)x));
        if (e > worst) {
            worst = e;
            at = x;
        }
    }
    printf("tanh: max abs error %.3g at %.6f over [-12, 12] step 1e-5\n", worst, at);
    CHECK(worst <= 4e-7);
    CHECK(fabs(pc_tanh(1e30f) - 1.0) <= 4e-7 && fabs(pc_tanh(-1e30f) + 1.0) <= 4e-7);
    CHECK(pc_tanh(8.5f) <= 1.0f && pc_tanh(100.0f) <= 1.0f);
    CHECK(pc_tanh(0.0f) == 0.0f);
    CHECK(isnan(pc_tanh(NAN)));
    for (i = 0; i < 1000; i++) {
        const float x = (float)i * 0.0123f;
        CHECK(pc_tanh(-x) == -pc_tanh(x));
    }
}

static void test_load_and_run(void)
{
    static buf model;
    const float c[7] = {0.5f, -1.0f, 2.0f, 0.0f, 0.0f, 0.0f, 0.0f}; /* quaternion kept */
    float in[1000 * 7], out[1000 * 7];
    pc_model *m = NULL;
    pc_error err;
    size_t i;
    int raw, ok;
    for (raw = 0; raw < 2; raw++) {
        spec s = ADD;
        s.raw = raw;
        build(&model, &s, c);
        CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_OK);
        if (!m)
            return;
        fill_poses(in, 1000);
        CHECK(pc_run(m, in, 1000, out) == PC_OK);
        ok = 1;
        for (i = 0; i < 1000 * 7; i++)
            if (out[i] != f32(in[i] + c[i % 7]))
                ok = 0;
        CHECK(ok);
        /* every n up to 40 (chunk decomposition), exact */
        for (i = 1; i <= 40; i++) {
            size_t j;
            memset(out, 0, sizeof out);
            CHECK(pc_run(m, in + 7, i, out) == PC_OK);
            ok = 1;
            for (j = 0; j < i * 7; j++)
                if (out[j] != f32(in[7 + j] + c[j % 7]))
                    ok = 0;
            CHECK(ok);
        }
        /* in-place */
        memcpy(out, in, 10 * 7 * sizeof(float));
        CHECK(pc_run(m, out, 10, out) == PC_OK && out[0] == f32(in[0] + c[0]) && out[3] == in[3]);
        /* a partial overlap of several poses: refused, out untouched (a later pose would be
         * read after an earlier one's output was written over it); of one pose: answered,
         * its input read whole before its output is written */
        memcpy(out, in, 11 * 7 * sizeof(float));
        CHECK(pc_run(m, out, 10, out + 7) == PC_ERR_ARGUMENT && out[7] == in[7]);
        CHECK(strstr(pc_model_message(m), "out overlaps in") != NULL);
        CHECK(pc_run(m, out + 7, 10, out) == PC_ERR_ARGUMENT && out[0] == in[0]);
        CHECK(pc_run(m, out, 1, out + 3) == PC_OK && out[3] == f32(in[0] + c[0]) &&
              out[5] == f32(in[2] + c[2]) && out[6] == in[3]);
        /* n = 0 is a no-op */
        out[0] = 42.0f;
        CHECK(pc_run(m, NULL, 0, NULL) == PC_OK);
        CHECK(pc_run(m, in, 0, out) == PC_OK && out[0] == 42.0f);
        /* NaN and inf: error, output untouched */
        for (i = 0; i < 3 * 7; i++)
            out[i] = -7.0f;
        in[2 * 7 + 5] = NAN;
        CHECK(pc_run(m, in, 3, out) == PC_ERR_NONFINITE);
        CHECK(strstr(pc_model_message(m), "pose 2") != NULL);
        in[2 * 7 + 5] = -INFINITY;
        CHECK(pc_run(m, in, 3, out) == PC_ERR_NONFINITE);
        /* a success, even of no pose, leaves no message of the failure before it */
        CHECK(pc_run(m, in, 0, out) == PC_OK && pc_model_message(m)[0] == '\0');
        ok = 1;
        for (i = 0; i < 3 * 7; i++)
            if (out[i] != -7.0f)
                ok = 0;
        CHECK(ok);
        CHECK(pc_run(m, in, 1, NULL) == PC_ERR_ARGUMENT);
        CHECK(pc_run(NULL, in, 1, out) == PC_ERR_ARGUMENT);
        /* a model without the input t ignores the times, unchecked */
        {
            const float never[2] = {NAN, INFINITY};
            CHECK(pc_run_timed(m, in, never, 2, out) == PC_OK && out[0] == f32(in[0] + c[0]));
            CHECK(pc_run_timed(m, in, never, 1, out) == PC_OK);
        }
        /* metadata */
        CHECK(pc_metadata_count(m) == 1);
        CHECK(strcmp(pc_metadata_key(m, 0), "method") == 0);
        CHECK(strcmp(pc_metadata_lookup(m, "method"), "pmc") == 0);
        CHECK(pc_metadata_lookup(m, "nope") == NULL && pc_metadata_key(m, 1) == NULL);
        CHECK(pc_max_batch(m) == PC_DEFAULT_MAX_BATCH && pc_arena_bytes(m) > 0);
        pc_free(m);
        m = NULL;
    }
    {
        pc_options o = ALLOW;
        o.max_batch = 100; /* rounds down to 64 */
        build(&model, &ADD, c);
        CHECK(pc_load_memory(model.d, model.n, &o, &m, &err) == PC_OK && pc_max_batch(m) == 64);
        pc_free(m);
    }
}

/* Counts the library's heap calls: it is linked statically into this program, so its
 * malloc and free resolve here (glibc; sanitizers bring their own allocator). */
#if defined(__GLIBC__) && !defined(__SANITIZE_ADDRESS__)
#define PC_COUNT_MALLOC 1
extern void *__libc_malloc(size_t size);
extern void *__libc_calloc(size_t n, size_t size);
extern void *__libc_realloc(void *p, size_t size);
static size_t n_heap_calls;
void *malloc(size_t size)
{
    n_heap_calls++;
    return __libc_malloc(size);
}
void *calloc(size_t n, size_t size)
{
    n_heap_calls++;
    return __libc_calloc(n, size);
}
void *realloc(void *p, size_t size)
{
    n_heap_calls++;
    return __libc_realloc(p, size);
}
#endif

static void test_load_into(void)
{
    static buf model;
    static unsigned char arena[1 << 20];
    const float c[7] = {0.5f, -1.0f, 2.0f, 0.0f, 0.0f, 0.0f, 0.0f};
    float in[40 * 7], out[40 * 7];
    pc_model *m = NULL, *small = (pc_model *)1;
    pc_error err;
    size_t need = 0, i;
    int ok = 1;
    build(&model, &ADD, c);
    CHECK(pc_version() == PC_VERSION_NUMBER);
    CHECK(pc_required_bytes(model.d, model.n, &ALLOW, &need, &err) == PC_OK);
    CHECK(need > 0 && need <= sizeof arena);
    CHECK(pc_load_into(model.d, model.n, &ALLOW, arena, need / 2, &small, &err) == PC_ERR_MEMORY);
    CHECK(small == NULL && strstr(err.message, "too small") != NULL);
#ifdef PC_COUNT_MALLOC
    n_heap_calls = 0; /* the counter sees the library's calls */
    CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_OK && n_heap_calls > 0);
    pc_free(m);
    n_heap_calls = 0;
#endif
    CHECK(pc_load_into(model.d, model.n, &ALLOW, arena + 1, need, &m, &err) == PC_OK);
    fill_poses(in, 40);
    CHECK(m && pc_run(m, in, 40, out) == PC_OK);
#ifdef PC_COUNT_MALLOC
    CHECK(n_heap_calls == 0);
#endif
    for (i = 0; m && i < 40 * 7; i++)
        if (out[i] != f32(in[i] + c[i % 7]))
            ok = 0;
    CHECK(ok);
    CHECK((unsigned char *)m >= arena && (unsigned char *)m + pc_arena_bytes(m) <= arena + 1 + need);
    /* the scratch before the model is the caller's again */
    memset(arena, 0xA5, (size_t)((unsigned char *)m - arena));
    CHECK(m && pc_run(m, in, 40, out) == PC_OK && out[7] == f32(in[7] + c[0]));
    pc_free(m); /* a no-op: the caller owns the buffer */
    CHECK(pc_load_into(model.d, model.n, &ALLOW, NULL, need, &m, &err) == PC_ERR_ARGUMENT);
}

/* pc_run of one pose on a model: status, and the message holds fragment. */
static void expect_run(pc_model *m, const float *pose, pc_status want, const char *fragment)
{
    float out[7] = {-7.0f, -7.0f, -7.0f, -7.0f, -7.0f, -7.0f, -7.0f};
    const pc_status st = pc_run(m, pose, 1, out);
    CHECK(st == want);
    CHECK(strstr(pc_model_message(m), fragment) != NULL);
    if (want != PC_OK)
        CHECK(out[0] == -7.0f && out[6] == -7.0f); /* refused before anything is written */
    if (st != want || !strstr(pc_model_message(m), fragment))
        fprintf(stderr, "  got %s: %s\n", pc_status_name(st), pc_model_message(m));
}

/* The load-time and pose checks that come from the weights and the metadata. */
static void test_checks(void)
{
    static buf model;
    float c[7] = {0};
    const float unit[7] = {0.5f, -0.25f, 0.0f, 1.0f, 0.0f, 0.0f, 0.0f};
    float pose[7];
    pc_model *m = NULL;
    pc_error err;
    int raw;
    /* non-finite weights, raw_data or float_data: refused at load, naming the element */
    for (raw = 0; raw < 2; raw++) {
        spec s = ADD;
        s.raw = raw;
        c[4] = raw ? NAN : -INFINITY;
        build(&model, &s, c);
        CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_ERR_MALFORMED && !m);
        CHECK(strstr(err.message, "tensor 'c' holds a non-finite value at element 4") != NULL);
    }
    c[4] = 0.0f;
    /* every model, whoever wrote it: input quaternions must be unit (norm within 1e-3) */
    build(&model, &ADD, c);
    CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_OK);
    if (m) {
        expect_run(m, unit, PC_OK, "");
        memcpy(pose, unit, sizeof pose);
        pose[3] = 3.0f;
        expect_run(m, pose, PC_ERR_QUATERNION, "pose 0: the quaternion qw, qx, qy, qz has norm "
                                               "3.000000 (expected a unit quaternion: norm "
                                               "within 0.001 of 1)");
        pose[3] = 0.0f;
        expect_run(m, pose, PC_ERR_QUATERNION, "norm 0.000000");
        pose[3] = 0.9995f; /* within the tables' tolerance */
        expect_run(m, pose, PC_OK, "");
        pc_free(m);
    }
    /* and output quaternions unit: a graph adding 0.25 to qw answers |q|^2 = 1.5625 */
    c[3] = 0.25f;
    build(&model, &ADD, c);
    CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_OK);
    if (m) {
        expect_run(m, unit, PC_ERR_RUNTIME, "pose 0: the quaternion qw, qx, qy, qz of output "
                                            "'corrected' is not unit (expected |q|^2 within "
                                            "0.002 of 1)");
        pc_free(m);
    }
    c[3] = 0.0f;
    /* input_bounds: a position outside is refused with the value and the bounds */
    build_meta(&model, &ADD, c, "input_bounds", "[[-1, -1, -1], [1, 1, 1.5]]");
    CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_OK);
    if (m) {
        memcpy(pose, unit, sizeof pose);
        pose[2] = 2.0f;
        expect_run(m, pose, PC_ERR_RANGE, "pose 0: z = 2.000 m is outside the range the model was "
                                          "fitted on, -1.000 to 1.500 m (metadata input_bounds)");
        pose[2] = -1.0625f;
        expect_run(m, pose, PC_ERR_RANGE, "z = -1.063 m");
        pose[2] = -3e30f;
        expect_run(m, pose, PC_ERR_RANGE, "z = -3.000e30 m");
        pose[2] = 1.5f;
        expect_run(m, pose, PC_OK, "");
        /* SteamVR's "no pose", all zeros but for a position outside: its quaternion is named,
         * before the box; a value not finite before both */
        pose[0] = 5.0f;
        pose[3] = 0.0f;
        expect_run(m, pose, PC_ERR_QUATERNION, "pose 0: the quaternion qw, qx, qy, qz has norm "
                                               "0.000000");
        pose[5] = NAN;
        expect_run(m, pose, PC_ERR_NONFINITE, "pose 0: qy is not finite (expected a finite "
                                              "number)");
        /* in a call of several poses, the pose's index in it */
        {
            float three[21], out[21];
            memcpy(three, unit, sizeof unit);
            memcpy(three + 7, unit, sizeof unit);
            memcpy(three + 14, unit, sizeof unit);
            three[15] = -2.0f;
            CHECK(pc_run(m, three, 3, out) == PC_ERR_RANGE);
            CHECK(strncmp(pc_model_message(m), "pose 2: y = -2.000 m is outside", 31) == 0);
        }
        pc_free(m);
    }
    /* bounds edited into NaN, infinity, an inverted box or the wrong count: refused */
    {
        static const char *const bad[][2] = {
            {"input_bounds", "[[-1, -1, -1], [1, 1, 1e39]]"},
            {"input_bounds", "[[-1e400, -1, -1], [1, 1, 1]]"},
            {"input_bounds", "[[nan, -1, -1], [1, 1, 1]]"},
            {"input_bounds", "[[-1, 1, -1], [1, -1, 1]]"},
            {"input_bounds", "[[-1, -1], [1, 1]]"},
            {"time_bounds", "[5, 1]"},
            {"time_bounds", "[0, 1e300]"},
            {"time_bounds", "[0, 1, 2]"},
            {"correction_reach", "[-1, 1]"},
            {"correction_reach", "[1, 1e39]"},
            {"correction_reach", "[1]"},
        };
        size_t k;
        for (k = 0; k < sizeof bad / sizeof bad[0]; k++) {
            m = NULL;
            build_meta(&model, &ADD, c, bad[k][0], bad[k][1]);
            CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_ERR_MALFORMED && !m);
            CHECK(strstr(err.message, bad[k][0]) != NULL);
        }
    }
    /* time_bounds of a model without the input t: read, checked, not applied */
    build_meta(&model, &ADD, c, "time_bounds", "[10, 20]");
    CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_OK);
    if (m) {
        const float t = 1e6f;
        CHECK(pc_run_timed(m, unit, &t, 1, pose) == PC_OK);
        pc_free(m);
    }
}

/* appends one metadata entry to a built model */
static void add_meta(buf *model, const char *key, const char *value)
{
    buf meta = {{0}, 0};
    put_str(&meta, 1, key);
    put_str(&meta, 2, value);
    put_msg(model, 14, &meta);
}

/* writes the digest over the "crc32c:00000000" placeholder (docs/design.md, "Integrity");
 * returns the offset of its eight digits */
static size_t sign(buf *model)
{
    static const char hex[] = "0123456789abcdef";
    size_t at, k;
    uint32_t crc;
    for (at = 0; at + 15 <= model->n; at++)
        if (memcmp(model->d + at, "crc32c:00000000", 15) == 0)
            break;
    at += 7;
    crc = pc_crc32c(0, model->d, model->n);
    for (k = 0; k < 8; k++)
        model->d[at + k] = (unsigned char)hex[crc >> (28 - 4 * k) & 15u];
    return at;
}

/* What every model must carry or be allowed without, the digest and the reach. */
static void test_contract(void)
{
    static buf model;
    const float c[7] = {0.5f, -1.0f, 2.0f, 0.0f, 0.0f, 0.0f, 0.0f};
    const float unit[7] = {0.5f, -0.25f, 0.0f, 1.0f, 0.0f, 0.0f, 0.0f};
    const pc_options unbounded = {0, PC_LOAD_ALLOW_UNBOUNDED, 0};
    const pc_options unsigned_ = {0, PC_LOAD_ALLOW_UNSIGNED, 0};
    pc_model *m = NULL;
    pc_error err;
    size_t at;
    CHECK(pc_crc32c(0, "123456789", 9) == 0xE3069283u);
    CHECK(pc_crc32c(pc_crc32c(0, "1234", 4), "56789", 5) == 0xE3069283u);
    /* no digest: refused unless allowed, the flag named */
    build(&model, &ADD, c);
    CHECK(pc_load_memory(model.d, model.n, &unbounded, &m, &err) == PC_ERR_INTEGRITY && !m);
    CHECK(strstr(err.message, "no metadata model_digest") && strstr(err.message, "PC_LOAD_ALLOW_UNSIGNED"));
    /* no bounds, no reach: refused unless allowed, the flag named */
    CHECK(pc_load_memory(model.d, model.n, &unsigned_, &m, &err) == PC_ERR_CONTRACT && !m);
    CHECK(strstr(err.message, "no metadata input_bounds") && strstr(err.message, "PC_LOAD_ALLOW_UNBOUNDED"));
    build_meta(&model, &ADD, c, "input_bounds", "[[-1, -1, -1], [1, 1, 1]]");
    CHECK(pc_load_memory(model.d, model.n, &unsigned_, &m, &err) == PC_ERR_CONTRACT && !m);
    CHECK(strstr(err.message, "no metadata correction_reach") != NULL);
    /* signed and bounded: loads with no flag; the correction of |(0.5, -1, 2)| = 2.291 m
     * is beyond a reach of 0.1 m */
    add_meta(&model, "correction_reach", "[0.1, 0.5]");
    add_meta(&model, "model_digest", "crc32c:00000000");
    at = sign(&model);
    CHECK(pc_load_memory(model.d, model.n, NULL, &m, &err) == PC_OK);
    if (m) {
        expect_run(m, unit, PC_ERR_RUNTIME, "pose 0: output 'corrected' moves the pose by 2.291 m "
                                            "and 0.000 rad, beyond the model's reach of 0.100 m "
                                            "and 0.500 rad (metadata correction_reach)");
        pc_free(m);
    }
    /* one byte changed anywhere (here a weight's): the digest no longer matches */
    model.d[model_without_meta / 2] ^= 0x01;
    CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_ERR_INTEGRITY && !m);
    CHECK(strstr(err.message, "model_digest says crc32c:") && strstr(err.message, "changed"));
    model.d[model_without_meta / 2] ^= 0x01;
    model.d[at] = model.d[at] == 'f' ? 'e' : 'f'; /* the digest itself edited */
    CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_ERR_INTEGRITY && !m);
    model.d[at] = 'G'; /* not hexadecimal */
    CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_ERR_INTEGRITY && !m);
    CHECK(strstr(err.message, "expected crc32c: and 8 lowercase hexadecimal digits") != NULL);
    /* a bound given twice: refused (the checks would take one, pc_metadata_lookup the other) */
    build_meta(&model, &ADD, c, "input_bounds", "[[-1, -1, -1], [1, 1, 1]]");
    add_meta(&model, "input_bounds", "[[-1, 0, -1], [1, 1, 1]]");
    CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_ERR_MALFORMED && !m);
    CHECK(strcmp(err.message, "metadata input_bounds appears twice") == 0);
    /* a reach that allows the correction: answered */
    build_meta(&model, &ADD, c, "correction_reach", "[2.5, 0.01]");
    CHECK(pc_load_memory(model.d, model.n, &ALLOW, &m, &err) == PC_OK);
    if (m) {
        expect_run(m, unit, PC_OK, "");
        pc_free(m);
    }
}

static void expect_error(const spec *s, pc_status want, const char *fragment)
{
    static buf model;
    const float c[7] = {0};
    pc_model *m = (pc_model *)1;
    pc_error err;
    pc_status st;
    build(&model, s, c);
    st = pc_load_memory(model.d, model.n, &ALLOW, &m, &err);
    CHECK(st == want);
    CHECK(m == NULL);
    CHECK(strstr(err.message, fragment) != NULL);
    if (st != want || !strstr(err.message, fragment))
        fprintf(stderr, "  got %s: %s\n", pc_status_name(st), err.message);
}

static void test_errors(void)
{
    static buf model;
    const float c[7] = {0};
    spec s;
    pc_model *m;
    pc_error err;
    size_t i;
    s = ADD; s.op = "Pow";
    expect_error(&s, PC_ERR_UNSUPPORTED, "unsupported operator Pow in node 'node0'");
    s = ADD; s.in_name = "measured";
    expect_error(&s, PC_ERR_CONTRACT, "'measured'");
    s = ADD; s.in_width = 6;
    expect_error(&s, PC_ERR_CONTRACT, "[N,7]");
    s = ADD; s.node_input = "ghost";
    expect_error(&s, PC_ERR_GRAPH, "input 'ghost' of node 'node0' is not produced");
    s = ADD; s.self_loop = 1;
    expect_error(&s, PC_ERR_GRAPH, "cycle");
    s = ADD; s.op = "Neg"; s.with_const = 1; s.node_input = "c";
    expect_error(&s, PC_ERR_GRAPH, "needs 1 input");
    /* truncated at every length: an error naming a byte, never success */
    build(&model, &ADD, c);
    for (i = 0; i < model.n; i++) {
        pc_status st = pc_load_memory(model.d, i, &ALLOW, &m, &err);
        /* Only a cut exactly at the end of a whole field can parse. */
        CHECK(st != PC_OK || i == model_without_meta);
        if (st == PC_OK)
            pc_free(m);
        if (st == PC_ERR_TRUNCATED)
            CHECK(strstr(err.message, "byte") != NULL);
    }
    /* bytes whose top level is no ModelProto: said so, then where the reader stopped; a
     * model cut short keeps its own words (above) */
    {
        static const unsigned char no_graph[] = {0x08, 0x07}; /* ir_version 7, nothing else */
        const char *text = "hello, this is not a model\n";
        CHECK(pc_load_memory(text, strlen(text), &ALLOW, &m, &err) == PC_ERR_MALFORMED && !m);
        CHECK(strcmp(err.message, "not a valid ONNX model (unsupported wire type 4 at byte 2)") == 0);
        CHECK(pc_load_memory(no_graph, sizeof no_graph, &ALLOW, &m, &err) == PC_ERR_MALFORMED);
        CHECK(strcmp(err.message, "not a valid ONNX model (no graph)") == 0);
        CHECK(pc_load_memory("8 is not", 8, &ALLOW, &m, &err) == PC_ERR_MALFORMED);
        CHECK(strcmp(err.message, "not a valid ONNX model (model field 7 at byte 0 is not bytes)")
              == 0);
    }
    CHECK(pc_load_memory(NULL, 10, NULL, &m, &err) == PC_ERR_ARGUMENT);
    CHECK(pc_load_memory(model.d, model.n, NULL, NULL, &err) == PC_ERR_ARGUMENT);
    CHECK(pc_load_file("/nonexistent/model.onnx", NULL, &m, &err) == PC_ERR_IO);
    CHECK(strstr(err.message, "/nonexistent/model.onnx") != NULL);
#if defined(__unix__) || defined(__APPLE__)
    CHECK(strstr(err.message, ": No such file or directory") != NULL); /* the cause, not only the path */
#endif
}

/* The centre of the positions and times a model was fitted on (its metadata "input_bounds"
 * and "time_bounds"): a pose there is one pc_run_timed must accept. Zero where the model
 * records no bounds. */
static void fitted_centre(const pc_model *m, float p[3], float *t)
{
    const char *box = pc_metadata_lookup(m, "input_bounds");
    const char *span = pc_metadata_lookup(m, "time_bounds");
    double lo[3], hi[3];
    int k;
    p[0] = p[1] = p[2] = *t = 0.0f;
    if (box && sscanf(box, " [ [ %lf , %lf , %lf ] , [ %lf , %lf , %lf ] ]", &lo[0], &lo[1],
                      &lo[2], &hi[0], &hi[1], &hi[2]) == 6)
        for (k = 0; k < 3; k++)
            p[k] = (float)(0.5 * (lo[k] + hi[k]));
    if (span && sscanf(span, " [ %lf , %lf ]", &lo[0], &hi[0]) == 2)
        *t = (float)(0.5 * (lo[0] + hi[0]));
}

int main(int argc, char **argv)
{
    test_varint();
    test_fields();
    test_status_names();
    test_format();
    test_tanh();
    test_load_and_run();
    test_load_into();
    test_checks();
    test_contract();
    test_errors();
    /* model files given on the command line must load and run at the centre of the
     * positions they were fitted on */
    {
        int a;
        for (a = 1; a < argc; a++) {
            pc_model *m;
            pc_error err;
            float in[7] = {0.0f, 0.0f, 0.0f, 1.0f, 0.0f, 0.0f, 0.0f}, out[7], t = 0.0f;
            /* pc_load_file frees the file's bytes once loaded: it loads a copy whatever
             * PC_LOAD_IN_PLACE says; program_ops beyond PC_MAX_PROGRAM_OPS is taken as
             * that bound, not as no programs */
            const pc_options in_place = {0, PC_LOAD_IN_PLACE, 0};
            const pc_options most = {0, 0, PC_MAX_PROGRAM_OPS}, beyond = {0, 0, (size_t)-1};
            pc_model *again, *capped, *huge;
            float again_out[7];
            CHECK(pc_load_file(argv[a], NULL, &m, &err) == PC_OK);
            CHECK(pc_load_file(argv[a], &in_place, &again, &err) == PC_OK);
            CHECK(pc_load_file(argv[a], &most, &capped, &err) == PC_OK);
            CHECK(pc_load_file(argv[a], &beyond, &huge, &err) == PC_OK);
            if (m && again && capped && huge) {
                fitted_centre(m, in, &t);
                CHECK(pc_run_timed(m, in, &t, 1, out) == PC_OK);
                CHECK(pc_run_timed(again, in, &t, 1, again_out) == PC_OK &&
                      memcmp(out, again_out, sizeof out) == 0);
                CHECK(pc_step_count(huge) == pc_step_count(capped) &&
                      pc_arena_bytes(huge) == pc_arena_bytes(capped));
            }
            pc_free(m);
            pc_free(again);
            pc_free(capped);
            pc_free(huge);
        }
    }
    printf("%d passed, %d failed\n", n_pass, n_fail);
    return n_fail ? 1 : 0;
}
