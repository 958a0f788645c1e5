/* Internal declarations shared by the library's translation units. Not installed. */
#ifndef PC_INTERNAL_H
#define PC_INTERNAL_H

#include "posecorr.h"

#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <math.h>
#include <stdio.h>

#define PC_MAX_RANK 6
#define PC_ALIGN 32
#define PC_PLAN_STRIDE 16

pc_status pc_fail(pc_error *err, pc_status status, const char *fmt, ...)
#ifdef __GNUC__
    __attribute__((format(printf, 3, 4)))
#endif
    ;

/* ---- protobuf wire format (pb_reader.c) ------------------------------------------- */

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
} pb_reader;

typedef struct pb_field {
    uint32_t number;
    uint32_t wire;
    uint64_t varint;   /* PB_VARINT, or the raw bits of PB_FIXED32 / PB_FIXED64 */
    pb_slice bytes;    /* PB_BYTES */
    size_t offset;     /* byte offset of the tag in the file */
} pb_field;

void pb_init(pb_reader *r, const uint8_t *file, pb_slice msg);
/* *more = 0 at the clean end of the message. */
pc_status pb_next(pb_reader *r, pb_field *f, int *more, pc_error *err);
pc_status pb_read_varint(pb_reader *r, uint64_t *v, pc_error *err);
int pb_slice_eq(pb_slice s, const char *z);
float pb_bits_to_float(uint32_t bits);

/* Repeated scalar fields may be packed (one PB_BYTES field) or not (one field per
 * element); these count and decode both forms from a field already read. */
pc_status pb_count_packed(const uint8_t *file, const pb_field *f, uint32_t elem_wire,
                          size_t *count, pc_error *err);
pc_status pb_decode_repeated(const uint8_t *file, const pb_field *f, uint32_t elem_wire,
                             int64_t *ints, float *floats, size_t cap, size_t *n,
                             pc_error *err);

/* ---- load-time scratch memory (model.c) -------------------------------------------- */

typedef struct pc_scratch_block pc_scratch_block;
typedef struct pc_scratch {
    pc_scratch_block *head;
    size_t used_total;
} pc_scratch;

void *pc_scratch_alloc(pc_scratch *s, size_t size);     /* zeroed */
void *pc_scratch_alloc_raw(pc_scratch *s, size_t size); /* not zeroed */
void pc_scratch_release(pc_scratch *s);

/* ---- graph under construction (graph.c) ------------------------------------------- */

typedef enum pc_dtype {
    PC_F32 = 1,
    PC_I64 = 7,
    PC_BOOL = 9
} pc_dtype;

size_t pc_dtype_size(int dtype);
const char *pc_dtype_name(int dtype);

typedef struct pc_value {
    pb_slice name;
    int dtype;          /* 0 until known */
    int rank;
    int64_t dims[PC_MAX_RANK];
    size_t count;
    void *cdata;        /* constant contents (scratch), NULL for run-time values */
    int producer;       /* node index, -1 for graph input / initializer */
    int consumers;      /* live, unfolded consumers (+1 for the graph output) */
    /* per-plan bookkeeping */
    int32_t alias;      /* value whose storage this one shares, or -1 */
    int32_t def, last;  /* step index of definition and last use */
    size_t offset;      /* offset in the activation region */
    int32_t const_slot; /* offset index in the constant region, -1 until used */
    size_t const_offset;
} pc_value;

typedef enum pc_act {
    PC_ACT_NONE = 0,
    PC_ACT_TANH,
    PC_ACT_SIGMOID,
    PC_ACT_RELU,
    PC_ACT_CLIP
} pc_act;

typedef struct pc_node {
    pb_slice name, op_type, domain;
    int op;
    uint32_t n_in, n_out, n_attr;
    int32_t *in;        /* value ids, -1 for an omitted optional input */
    int32_t *out;
    pb_slice *attr;     /* AttributeProto messages, parsed on demand */
    pb_slice *in_names, *out_names;
    int live, folded, fused_away;
    int act;
    float act_lo, act_hi;
} pc_node;

typedef struct pc_meta {
    pb_slice key, value;
} pc_meta;

typedef struct pc_step pc_step;
typedef pc_status (*pc_kernel_fn)(const pc_step *s);

/* Run-time form of one kernel launch: everything resolved at load. */
struct pc_step {
    pc_kernel_fn fn;
    void *const *io;    /* inputs then outputs */
    const void *prm;    /* operator parameters (no pointers inside) */
    size_t n;           /* element count of output 0 */
};

typedef struct pc_draft {
    pc_kernel_fn fn;
    int32_t *io;        /* value ids: inputs then outputs */
    uint32_t n_io;
    void *prm;
    size_t prm_size;
    size_t n;
} pc_draft;

typedef struct pc_derived {
    int32_t src;
    int kind;
    int32_t id;
} pc_derived;

typedef struct pc_builder {
    pc_scratch scratch;
    pc_error *err;
    const uint8_t *file;
    size_t file_size;
    int64_t opset;
    pc_node *nodes;
    size_t n_nodes;
    pc_value *values;
    size_t n_values, cap_values;
    int32_t *order;     /* topological order of nodes */
    pc_meta *meta;
    size_t n_meta;
    int32_t *hash;      /* name -> value id, open addressing */
    size_t hash_cap;
    int32_t input_id, output_id;
    pc_derived *derived;
    size_t n_derived, cap_derived;
    int cpu_avx2;       /* -1 until asked */
    /* current plan */
    pc_draft *drafts;
    size_t n_drafts;    /* at most one launch per node */
} pc_builder;

typedef struct pc_prep {
    pc_builder *b;
    pc_node *node;
    size_t n_in, n_out;
    int32_t *in_ids;    /* may be replaced by derived constants */
    int32_t *out_ids;
    pc_value **in;      /* NULL for an omitted optional input */
    pc_value **out;
    pc_kernel_fn fn;
    void *prm;
    size_t prm_size;
    int32_t alias_of;   /* output 0 is a view of this value (no kernel) */
    int folding;
    /* extra leading inputs used only by the kernel (e.g. after derivation) */
} pc_prep;

/* Helpers for operator prepare functions (graph.c). */
pc_status pc_prep_fail(pc_prep *p, pc_status st, const char *fmt, ...)
#ifdef __GNUC__
    __attribute__((format(printf, 3, 4)))
#endif
    ;
int pc_attr_find(pc_prep *p, const char *name, pb_field *value, int *type);
pc_status pc_attr_int(pc_prep *p, const char *name, int64_t def, int64_t *out);
pc_status pc_attr_float(pc_prep *p, const char *name, float def, float *out);
pc_status pc_attr_ints(pc_prep *p, const char *name, int64_t *buf, size_t cap, size_t *n,
                       int *found);
pc_status pc_attr_floats(pc_prep *p, const char *name, float *buf, size_t cap, size_t *n,
                         int *found);
pc_status pc_attr_tensor(pc_prep *p, const char *name, pb_slice *tensor, int *found);
int pc_has_attr(pc_prep *p, const char *name);
pc_status pc_input_ints(pc_prep *p, size_t k, int64_t *buf, size_t cap, size_t *n);
pc_status pc_input_float_scalar(pc_prep *p, size_t k, float *out);
pc_status pc_set_out(pc_prep *p, size_t k, int dtype, int rank, const int64_t *dims);
void *pc_prep_params(pc_prep *p, size_t size);
pc_status pc_new_const(pc_prep *p, int dtype, int rank, const int64_t *dims, void **data,
                       int32_t *id);
int32_t pc_find_derived(pc_builder *b, int32_t src, int kind);
pc_status pc_add_derived(pc_builder *b, int32_t src, int kind, int32_t id);
pc_status pc_alloc_const(pc_builder *b, pb_slice name, int dtype, int rank,
                         const int64_t *dims, int32_t *id);
pc_status pc_tensor_to_const(pc_builder *b, pb_slice tensor, int32_t *id);

/* Kernels that only unusual graphs reach are built for size inside optimised files. */
#if defined(__GNUC__) && !defined(__clang__)
#define PC_COLD __attribute__((optimize("Os")))
#else
#define PC_COLD
#endif

/* ---- broadcasting kernels (layout chosen at load, ops.c; float kernels, kernels.c) --- */

/* Operand layouts of a broadcast op, after coalescing dimensions. ROW_B: B is one row
 * repeated over the rows of A ([M,K] op [K]); COL_B: B is one value per row of A
 * ([M,K] op [M,1]). GENERAL2: at most two coalesced dimensions. */
enum {
    PC_SAME = 0,
    PC_SCALAR_A,
    PC_SCALAR_B,
    PC_ROW_B,
    PC_COL_B,
    PC_GENERAL2,
    PC_GENERAL,
    PC_LAYOUTS
};

/* Output dims and per-operand strides, outermost first, padded to PC_MAX_RANK. */
typedef struct pc_bcast {
    size_t d[PC_MAX_RANK];
    size_t st[3][PC_MAX_RANK];
} pc_bcast;

#define PC_FOR6(q, K, BODY)                                                                     \
    do {                                                                                        \
        size_t i0, i1, i2, i3, i4, i5, o = 0, kk;                                               \
        for (i0 = 0; i0 < (q)->d[0]; i0++)                                                      \
            for (i1 = 0; i1 < (q)->d[1]; i1++)                                                  \
                for (i2 = 0; i2 < (q)->d[2]; i2++)                                              \
                    for (i3 = 0; i3 < (q)->d[3]; i3++)                                          \
                        for (i4 = 0; i4 < (q)->d[4]; i4++) {                                    \
                            size_t base[K];                                                     \
                            for (kk = 0; kk < (K); kk++)                                        \
                                base[kk] = i0 * (q)->st[kk][0] + i1 * (q)->st[kk][1] +          \
                                           i2 * (q)->st[kk][2] + i3 * (q)->st[kk][3] +          \
                                           i4 * (q)->st[kk][4];                                 \
                            for (i5 = 0; i5 < (q)->d[5]; i5++, o++) {                           \
                                BODY                                                            \
                            }                                                                   \
                        }                                                                       \
    } while (0)

#define PC_UNARY(NAME, TI, TO, EXPR)                                                           \
    pc_status NAME(const pc_step *s)                                                           \
    {                                                                                          \
        const TI *restrict A = (const TI *)s->io[0];                                           \
        TO *restrict O = (TO *)s->io[1];                                                       \
        size_t i;                                                                              \
        for (i = 0; i < s->n; i++) {                                                           \
            const TI a = A[i];                                                                 \
            O[i] = (TO)(EXPR);                                                                 \
        }                                                                                      \
        return PC_OK;                                                                          \
    }

/* Parameters of the data-movement operators (prepared in ops.c). */
typedef struct pc_strided {
    size_t d[PC_MAX_RANK];
    ptrdiff_t st[PC_MAX_RANK];
    ptrdiff_t base;
} pc_strided;

typedef struct pc_concat {
    size_t outer, n_in, total, esize;
    size_t inner[1]; /* n_in entries; allocated longer */
} pc_concat;

typedef struct pc_gather {
    size_t outer, len, inner, n_idx, esize;
} pc_gather;

typedef struct pc_reduce {
    size_t d[PC_MAX_RANK];
    size_t ost[PC_MAX_RANK];
} pc_reduce;

/* Elementwise loops written once for ops.c (integer, boolean, comparison) and kernels.c
 * (float); a use puts the storage class in front. */
#define PC_BINARY_SAME(NAME, TI, TO, EXPR)                                                     \
    pc_status NAME##_same(const pc_step *s)                                                    \
    {                                                                                          \
        const TI *restrict A = (const TI *)s->io[0];                                           \
        const TI *restrict B = (const TI *)s->io[1];                                           \
        TO *restrict O = (TO *)s->io[2];                                                       \
        size_t i;                                                                              \
        for (i = 0; i < s->n; i++) {                                                           \
            const TI a = A[i], b = B[i];                                                       \
            O[i] = (TO)(EXPR);                                                                 \
        }                                                                                      \
        return PC_OK;                                                                          \
    }

#define PC_BINARY_GEN(NAME, TI, TO, EXPR)                                                      \
    pc_status NAME##_gen(const pc_step *s)                                                     \
    {                                                                                          \
        const pc_bcast *q = (const pc_bcast *)s->prm;                                          \
        const TI *A = (const TI *)s->io[0];                                                    \
        const TI *B = (const TI *)s->io[1];                                                    \
        TO *O = (TO *)s->io[2];                                                                \
        PC_FOR6(q, 2, {                                                                        \
            const TI a = A[base[0] + i5 * q->st[0][5]];                                        \
            const TI b = B[base[1] + i5 * q->st[1][5]];                                        \
            O[o] = (TO)(EXPR);                                                                 \
        });                                                                                    \
        return PC_OK;                                                                          \
    }

#define PC_WHERE_SAME(NAME, T)                                                                 \
    pc_status NAME##_same(const pc_step *s)                                                    \
    {                                                                                          \
        const uint8_t *restrict C = (const uint8_t *)s->io[0];                                 \
        const T *restrict X = (const T *)s->io[1];                                             \
        const T *restrict Y = (const T *)s->io[2];                                             \
        T *restrict O = (T *)s->io[3];                                                         \
        size_t i;                                                                              \
        for (i = 0; i < s->n; i++)                                                             \
            O[i] = C[i] ? X[i] : Y[i];                                                         \
        return PC_OK;                                                                          \
    }

/* Float kernels of the hot elementwise operators, one per layout (kernels.c). */
#define PC_FLOAT_BINARY(X) X(k_add_f) X(k_sub_f) X(k_mul_f) X(k_div_f) X(k_max_f) X(k_min_f)
#define PC_DECLARE_TABLE(NAME) extern const pc_kernel_fn NAME[PC_LAYOUTS];
PC_FLOAT_BINARY(PC_DECLARE_TABLE)
#undef PC_DECLARE_TABLE
#define PC_FLOAT_UNARY(X)                                                                      \
    X(k_abs_f) X(k_neg_f) X(k_atan_f) X(k_cos_f) X(k_sin_f) X(k_tan_f) X(k_exp_f) X(k_sqrt_f) \
    X(k_relu_f) X(k_sigmoid_f) X(k_tanh_f)
#define PC_DECLARE_KERNEL(NAME) pc_status NAME(const pc_step *s);
PC_FLOAT_UNARY(PC_DECLARE_KERNEL)
PC_DECLARE_KERNEL(k_where_f_same)
PC_DECLARE_KERNEL(k_copy_4)        /* pc_strided: contiguous run */
PC_DECLARE_KERNEL(k_strided2_4)    /* pc_strided: two levels */
PC_DECLARE_KERNEL(k_concat)        /* pc_concat */
PC_DECLARE_KERNEL(k_gather_cols_4) /* pc_gather: 4-byte elements, inner 1, indices checked */
PC_DECLARE_KERNEL(k_reduce_sum_last) /* pc_reduce: innermost block */
#undef PC_DECLARE_KERNEL

/* ---- operators (ops.c) ------------------------------------------------------------ */

typedef pc_status (*pc_prepare_fn)(pc_prep *p);

static inline float pc_sigmoid(float x)
{
    return 1.0f / (1.0f + expf(-x));
}

/* Gemm / MatMul parameters and kernels (dense.c). */
typedef struct pc_gemm {
    size_t M, K, N;
    size_t a_rs, a_cs, b_rs, b_cs;
    int c_mode; /* 0 none, 1 scalar, 2 row [N], 3 column [M,1], 4 full [M,N] */
    float alpha, beta;
    int act;
    float lo, hi;
    /* MatMul batching over up to 4 broadcast batch dimensions */
    size_t nbd, bd[4], a_bst[4], b_bst[4];
} pc_gemm;
pc_status k_gemm(const pc_step *s);
/* The MLP layer act(A B + c), act tanh or none, in the widest variant this CPU runs. */
pc_kernel_fn pc_gemm_rows_kernel(pc_builder *b);
pc_status k_matmul(const pc_step *s);


enum {
#define PC_OP(name) PC_OP_##name,
#include "pc_operators.def"
#undef PC_OP
    PC_OP_COUNT
};

typedef struct pc_op_info {
    const char *name;
    pc_prepare_fn prepare;
} pc_op_info;

extern const pc_op_info pc_ops[PC_OP_COUNT];
int pc_op_lookup(pb_slice name);
/* The kernels' tanh as a function, for the unit tests. */
float pc_tanh(float x);

/* tanh(x) = x P(x^2) / Q(x^2) on |x| <= 9, +-1 beyond (tanh(9) = 1 - 3e-8). Coefficients
 * fitted for this library by iteratively reweighted least squares towards minimax
 * absolute error (5.9e-9 in exact arithmetic, 3.2e-7 evaluated in float32). Branch-free
 * so that loops over it vectorise; NaN propagates through the clamps. */
static inline float pc_tanh_inline(float x)
{
    float c = x > 9.0f ? 9.0f : x;
    float t, p, q;
    c = c < -9.0f ? -9.0f : c;
    t = c * c;
    p = -8.291313e-14f;
    p = p * t + 5.1926935e-11f;
    p = p * t + -2.0029567e-08f;
    p = p * t + 1.1101826e-05f;
    p = p * t + 0.0030986548f;
    p = p * t + 0.13079165f;
    p = p * t + 0.99999994f;
    q = 0.00025386017f;
    q = q * t + 0.024473764f;
    q = q * t + 0.46412486f;
    q = q * t + 1.0f;
    p = c * p / q;
    /* |tanh| <= 1 must hold exactly: callers may feed it to acos-like maths. */
    p = p > 1.0f ? 1.0f : p;
    return p < -1.0f ? -1.0f : p;
}

/* ---- the loaded model (model.c, run.c) -------------------------------------------- */

typedef struct pc_plan {
    size_t batch;
    pc_step *steps;
    size_t n_steps;
    float *in;
    const float *out;
} pc_plan;

struct pc_model {
    size_t arena_bytes;
    size_t n_meta;
    const char **meta_key;
    const char **meta_value;
    size_t max_batch;
    size_t n_plans;
    pc_plan *plans;     /* batch 1, PC_PLAN_STRIDE, PC_PLAN_STRIDE^2, ..., max_batch */
    size_t n_nodes;
    char message[PC_MESSAGE_SIZE];
};

pc_status pc_build(pc_builder *b, const pc_options *opts, pc_model **model);
pc_status pc_parse_model(pc_builder *b);

#endif
