/* Layer 4, kernels: the run-time form of one kernel launch (pc_step), the parameter
 * blocks the operators fill at load, and the kernels shared by several operator families.
 * Knows nothing of ONNX or of the graph: a kernel only loops over its operands. */
#ifndef PC_KERNELS_H
#define PC_KERNELS_H

#include "base.h"
#include "formulas.h"

typedef struct pc_step pc_step;
typedef pc_status (*pc_kernel_fn)(const pc_step *s);

/* Run-time form of one kernel launch: everything resolved at load. */
struct pc_step {
    pc_kernel_fn fn;
    void *const *io;    /* inputs then outputs */
    const void *prm;    /* operator parameters (no pointers inside) */
    size_t n;           /* element count of output 0 */
};

/* Activations a dense kernel applies to its result (fused by the graph scan). */
typedef enum pc_act {
    PC_ACT_NONE = 0,
    PC_ACT_TANH,
    PC_ACT_SIGMOID,
    PC_ACT_RELU,
    PC_ACT_CLIP,
    PC_ACT_RADBAS /* exp(-(x * x)) */
} pc_act;

/* Kernels that only unusual graphs reach are built for size inside optimised files. */
#if defined(__GNUC__) && !defined(__clang__)
#define PC_COLD __attribute__((optimize("Os")))
#else
#define PC_COLD
#endif


/* ---- broadcasting kernels (layout chosen at load, op_elementwise.c; float kernels, kernels.c) */

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

/* Parameters of the data-movement operators (prepared in op_shape.c; pc_reduce in op_reduce.c). */
typedef struct pc_strided {
    size_t d[PC_MAX_RANK];
    ptrdiff_t st[PC_MAX_RANK];
    ptrdiff_t base;
} pc_strided;

typedef struct pc_concat {
    size_t outer, n_in, total, esize;
    int columns; /* 4-byte elements, every inner 1: [outer,1] x n_in -> [outer,n_in] */
    size_t inner[1]; /* n_in entries; allocated longer */
} pc_concat;

typedef struct pc_gather {
    size_t outer, len, inner, n_idx, esize;
} pc_gather;

typedef struct pc_reduce {
    size_t d[PC_MAX_RANK];
    size_t ost[PC_MAX_RANK];
} pc_reduce;

/* Elementwise loops written once for op_elementwise.c (integer, boolean, comparison) and kernels.c
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

/* One-pose programs (built by the planner, program.c): the small steps of a one-pose
 * plan flattened into element operations, interpreted in one launch. An entry reads the
 * elements at byte offsets a, b, c from the step's io[0] and writes the one at o; the
 * arithmetic is the kernels' own, so results are the steps' bit for bit. Entries come in
 * groups of one code, each after a header entry {a = code, b = entries of the group}. A
 * DOT entry starts o = c + a b; the entries after it whose o is PC_DOT_TERM add their
 * a b, in order. Codes start at 1: 0 means "no element form". */
enum {
    PC_SOP_NONE = 0,
    PC_SOP_ADD, PC_SOP_SUB, PC_SOP_MUL, PC_SOP_DIV, PC_SOP_MAX, PC_SOP_MIN,
    PC_SOP_EQ, PC_SOP_GT, PC_SOP_GE, PC_SOP_LT, PC_SOP_LE, /* bool output */
    PC_SOP_NEG, PC_SOP_SQRT, PC_SOP_ABS, PC_SOP_EXP, PC_SOP_SIN, PC_SOP_COS, PC_SOP_TAN,
    PC_SOP_ATAN, PC_SOP_TANH, PC_SOP_SIGMOID, PC_SOP_RELU,
    PC_SOP_WHERE,    /* c (bool) ? a : b */
    PC_SOP_COPY,     /* the 4 bytes at a */
    PC_SOP_COPY1,    /* the byte at a (a bool) */
    PC_SOP_DOT,      /* o = c + a b + (the terms after it) */
    PC_SOP_COUNT
};

/* Unary codes lie in [PC_SOP_NEG, PC_SOP_RELU]; binary ones before, bool-valued in
 * [PC_SOP_EQ, PC_SOP_LE]. */
#define PC_SOP_IS_BINARY(c) ((c) >= PC_SOP_ADD && (c) <= PC_SOP_LE)
#define PC_SOP_IS_BOOL(c) ((c) >= PC_SOP_EQ && (c) <= PC_SOP_LE)
#define PC_DOT_TERM INT32_MIN

typedef struct pc_scalar_op {
    int32_t a, b, c, o;
} pc_scalar_op;

typedef struct pc_scalar_program {
    size_t n_ops;
    pc_scalar_op ops[1]; /* n_ops entries; allocated longer */
} pc_scalar_program;

/* The same with 16-bit offsets, when every offset of a program fits. */
#define PC_DOT_TERM16 INT16_MIN
typedef struct pc_scalar_op16 {
    int16_t a, b, c, o;
} pc_scalar_op16;

typedef struct pc_scalar_program16 {
    size_t n_ops;
    pc_scalar_op16 ops[1];
} pc_scalar_program16;

pc_status k_scalar_program(const pc_step *s);
pc_status k_scalar_program16(const pc_step *s);
/* Element operation `code` (not DOT) on the four bytes of each operand: what the program
 * computes, computed while it is built (an operation whose operands are all constants). */
uint32_t pc_sop_eval(int code, uint32_t a, uint32_t b, uint32_t c);

#define PC_DECLARE_TABLE(NAME, CODE, EXPR) extern const pc_kernel_fn NAME[PC_LAYOUTS];
PC_FLOAT_BINARY_OPS(PC_DECLARE_TABLE)
#undef PC_DECLARE_TABLE
#define PC_DECLARE_UNARY(NAME, CODE, EXPR) pc_status NAME(const pc_step *s);
PC_FLOAT_UNARY_OPS(PC_DECLARE_UNARY)
#undef PC_DECLARE_UNARY
#define PC_DECLARE_KERNEL(NAME) pc_status NAME(const pc_step *s);
PC_DECLARE_KERNEL(k_where_f_same)
PC_DECLARE_KERNEL(k_copy_4)        /* pc_strided: contiguous run */
PC_DECLARE_KERNEL(k_strided2_4)    /* pc_strided: two levels */
PC_DECLARE_KERNEL(k_concat)        /* pc_concat */
PC_DECLARE_KERNEL(k_gather_cols_4) /* pc_gather: 4-byte elements, inner 1, indices checked */
PC_DECLARE_KERNEL(k_reduce_sum_last) /* pc_reduce: innermost block */
#undef PC_DECLARE_KERNEL

/* The kernels' tanh as a function, for the unit tests. */
float pc_tanh(float x);

/* Element operation `code` on floats, for a code known at compile time: the compiled
 * programs' arithmetic, from the same list as the kernels'. */
#ifdef __GNUC__
__attribute__((always_inline))
#endif
static inline float pc_sop_float(const int code, const float a, const float b)
{
    switch (code) {
#define PC_SOP_FLOAT_CASE(KERNEL, CODE, EXPR) case CODE: return (EXPR);
        PC_FLOAT_BINARY_OPS(PC_SOP_FLOAT_CASE)
        PC_FLOAT_UNARY_OPS(PC_SOP_FLOAT_CASE)
#undef PC_SOP_FLOAT_CASE
    default:
        return b;
    }
}

/* One-pose programs compiled ahead of time (programs_compiled.c, written by
 * tools/compile_programs.py from the shipped models' programs). A program whose shape
 * (program.c) equals `shape` runs `fn` instead of the interpreter: the same operations, its
 * own results kept in registers. Its parameters (s->prm) are what it reads from memory,
 * in the shape's order: an int16_t offset from the activations per arena operand and
 * per stored result (their count rounded up to even), then one float per constant
 * operand. A small target's arena keeps no entries for the operations in between. */
typedef struct pc_compiled_program {
    uint32_t n_bytes;
    uint64_t hash;       /* FNV-1a of shape */
    const uint8_t *shape;
    pc_kernel_fn fn;
} pc_compiled_program;
extern const pc_compiled_program pc_compiled_programs[];
extern const size_t pc_n_compiled_programs;

/* The layer sizes the project trains: the pose vectors of the representations (pos 3,
 * eaa 6, quat 7, zhou 9, R 12) and table 1's hidden widths (5, 10, 15, 20). */
#define PC_LAYER_SIZES(X) X(3) X(5) X(6) X(7) X(9) X(10) X(12) X(15) X(20)
#define PC_LAYER_SIZES_TEXT "3, 5, 6, 7, 9, 10, 12, 15, 20"
/* The one-pose layers with a specialised kernel (dense.c): into a hidden width from any
 * size, and from a hidden width out to a pose vector. */
#define PC_LAYER_SHAPES(X) \
    X(3, 5) X(3, 10) X(3, 15) X(3, 20) \
    X(5, 5) X(5, 10) X(5, 15) X(5, 20) \
    X(6, 5) X(6, 10) X(6, 15) X(6, 20) \
    X(7, 5) X(7, 10) X(7, 15) X(7, 20) \
    X(9, 5) X(9, 10) X(9, 15) X(9, 20) \
    X(10, 5) X(10, 10) X(10, 15) X(10, 20) \
    X(12, 5) X(12, 10) X(12, 15) X(12, 20) \
    X(15, 5) X(15, 10) X(15, 15) X(15, 20) \
    X(20, 5) X(20, 10) X(20, 15) X(20, 20) \
    X(5, 3) X(5, 6) X(5, 7) X(5, 9) X(5, 12) \
    X(10, 3) X(10, 6) X(10, 7) X(10, 9) X(10, 12) \
    X(15, 3) X(15, 6) X(15, 7) X(15, 9) X(15, 12) \
    X(20, 3) X(20, 6) X(20, 7) X(20, 9) X(20, 12)

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
/* The MLP layer act(A B + c), act tanh, sigmoid or none: [0] portable, [1] AVX2 (the
 * portable one again where AVX2 is not built). pc_cpu_avx2() says which this CPU runs. */
extern const pc_kernel_fn pc_gemm_rows_kernels[2];
/* One layer of a one-pose chain on its operands io = A, B, C, O. */
typedef void (*pc_layer_fn)(const pc_gemm *l, void *const *io);
typedef struct pc_chain_layer {
    pc_gemm g;
    pc_layer_fn fn;
} pc_chain_layer;
/* Consecutive MLP layers, each reading the one before's output, as one launch (one-pose
 * plans: the planner chains them): io holds A, B, C, O of each layer in turn. */
typedef struct pc_gemm_chain {
    size_t n_layers;
    pc_chain_layer layer[1]; /* n_layers entries; allocated longer */
} pc_gemm_chain;
pc_status k_gemm_chain(const pc_step *s);
/* The function that runs layer l of a one-pose chain: the specialised kernel of its K and N
 * (AVX2, PC_LAYER_SHAPES), else the general layer; *why says why not ("" when it is). */
pc_layer_fn pc_chain_layer_fn(const pc_gemm *l, int avx2, const char **why);
/* Why a built layer runs the general layer ("" when it runs a specialised kernel). */
const char *pc_chain_layer_why(const pc_chain_layer *l);
int pc_cpu_avx2(void);
pc_status k_matmul(const pc_step *s);

#endif
