/* posecorr-plan MODEL.onnx [--allow-unbounded] [--allow-unsigned]
 *
 * Loads a model for one pose at a time (max_batch 1) and prints the plan pc_run runs, so
 * that `posecorr compile` (python/posecorr/controller/to_c.py) writes the same work as C.
 * Operands are byte offsets from the activations ("a:OFF"), or constants, printed with
 * their float32 bits. One line each:
 *
 *   sop CODE NAME [EXPR]         an element operation's code, name and expression in a, b
 *   checks lo=X,Y,Z hi=X,Y,Z reach_pos2=W reach_cos2=W span=LO,HI|-
 *                                pc_run's input and reach checks, their numbers as pc_run
 *                                compares them (float32 bits; unbounded: infinities, 0)
 *   plan steps=N in=OFF t=OFF|- out=OFF
 *   step K program               a one-pose program; its entries follow:
 *   op CODE A B C O              element operation CODE (kernels.h PC_SOP_*) of the
 *   term A B                     operands at offsets A, B, C (negative: the pool), into O;
 *                                a term adds A B to the dot product before it
 *   pool LO W...                 the program constants' words from offset LO up to 0
 *   step K dense L               L layers of act(A B + C), one pose each:
 *   layer M K N ACT LO HI ALPHA BETA A B C O, with B as K x N and C as N values:
 *                                "a:OFF" or "k:" followed by the constant's words
 *   step K elements NAME         a node's kernel NAME of element arithmetic or copies of
 *                                4-byte elements: its work as op lines, as a program's
 *   step K kernel NAME           a kernel posecorr compile does not translate
 *
 * Exit status 1 with the runtime's message when the model does not load. */
#include "model.h"

#include <stdio.h>
#include <string.h>

static const char *kernel_name(pc_kernel_fn fn);

static int is_activation(const pc_model *m, const void *p)
{
    const uint8_t *u = (const uint8_t *)p;
    return u >= m->act && u < (const uint8_t *)m + m->arena_bytes;
}

static long offset_of(const pc_model *m, const void *p)
{
    return (long)((const uint8_t *)p - m->act);
}

static unsigned long bits(float f)
{
    uint32_t u;
    memcpy(&u, &f, 4);
    return (unsigned long)u;
}

/* An operand of a layer: its offset, or the `count` values it holds, element i at
 * p[i / per_row * row_stride + i % per_row * col_stride]. */
static void print_operand(const pc_model *m, const float *p, size_t count, size_t per_row,
                          size_t row_stride, size_t col_stride)
{
    size_t i;
    if (is_activation(m, p)) {
        printf(" a:%ld", offset_of(m, p));
        return;
    }
    printf(" k:");
    for (i = 0; i < count; i++)
        printf("%s%08lx", i ? "," : "",
               bits(p[i / per_row * row_stride + i % per_row * col_stride]));
}

static const size_t c_stride[5] = {0, 0, 1, 0, 1}; /* by c_mode: none, scalar, row, column, full */

/* A layer of one pose whose operands in the arena are read in order (the form printed). */
static int layer_ok(const pc_model *m, const pc_gemm *g, void *const *io, int has_c)
{
    return g->M == 1 && g->nbd == 0 && g->c_mode >= 0 && g->c_mode <= 4 &&
           (g->a_cs == 1 || !is_activation(m, io[0])) &&
           ((g->b_cs == 1 && g->b_rs == g->N) || !is_activation(m, io[1])) &&
           (!has_c || !g->c_mode || c_stride[g->c_mode] == 1 || !is_activation(m, io[2]));
}

/* act(alpha A B + beta C) of one pose; C as the N values row 0 adds. */
static void print_layer(const pc_model *m, const pc_gemm *g, void *const *io, int has_c)
{
    printf("layer %zu %zu %zu %d %08lx %08lx %08lx %08lx", g->M, g->K, g->N, g->act,
           bits(g->lo), bits(g->hi), bits(g->alpha), bits(g->beta));
    print_operand(m, (const float *)io[0], g->K, g->K, 0, g->a_cs);
    print_operand(m, (const float *)io[1], g->K * g->N, g->N, g->b_rs, g->b_cs);
    if (has_c && g->c_mode)
        print_operand(m, (const float *)io[2], g->N, g->N, 0, c_stride[g->c_mode]);
    else
        printf(" -");
    printf(" a:%ld\n", offset_of(m, io[has_c ? 3 : 2]));
}

static int is_program(pc_kernel_fn fn)
{
    return fn == k_scalar_program16;
}

/* One entry of a program's form; lo follows the lowest (pool) offset read. */
static void print_op(long *lo, int code, long a, long b, long c, long o)
{
    printf("op %d %ld %ld %ld %ld\n", code, a, b, c, o);
    *lo = a < *lo ? a : *lo;
    *lo = b < *lo ? b : *lo;
    *lo = c < *lo ? c : *lo;
}

/* The words from offset lo (negative: constants below the activations) up to 0. */
static void print_pool(const pc_model *m, long lo)
{
    uint32_t w;
    if (lo >= 0)
        return;
    printf("pool %ld", lo);
    for (; lo < 0; lo += 4) {
        memcpy(&w, m->act + lo, 4);
        printf(" %08lx", (unsigned long)w);
    }
    printf("\n");
}

#define PRINT_PROGRAM(NAME, PROGRAM, TERM)                                                     \
    static void NAME(const pc_model *m, const PROGRAM *q)                                      \
    {                                                                                          \
        size_t i = 0, end;                                                                     \
        long lo = 0;                                                                           \
        while (i < q->n_ops) {                                                                 \
            const int code = q->ops[i].a;                                                      \
            for (end = i + 1 + (size_t)q->ops[i].b, i++; i < end; i++) {                       \
                const long a = q->ops[i].a, b = q->ops[i].b, c = q->ops[i].c;                  \
                if (q->ops[i].o == (TERM)) {                                                   \
                    printf("term %ld %ld\n", a, b);                                            \
                    lo = a < lo ? a : lo;                                                      \
                    lo = b < lo ? b : lo;                                                      \
                } else {                                                                       \
                    print_op(&lo, code, a, b, c, (long)q->ops[i].o);                           \
                }                                                                              \
            }                                                                                  \
        }                                                                                      \
        print_pool(m, lo);                                                                     \
    }
PRINT_PROGRAM(print_program16, pc_scalar_program16, PC_DOT_TERM16)
PRINT_PROGRAM(print_program32, pc_scalar_program, PC_DOT_TERM)
#undef PRINT_PROGRAM

/* ---- node kernels whose work is element operations ------------------------------------ */

/* Byte offset of an operand from the activations; 0 when it lies outside the arena (a
 * constant read where it lies in the file). */
static int arena_offset(const pc_model *m, const void *p, long *off)
{
    const uint8_t *u = (const uint8_t *)p;
    if (u < (const uint8_t *)m || u >= (const uint8_t *)m + m->arena_bytes)
        return 0;
    *off = (long)(u - m->act);
    return 1;
}

/* The first n operands of a step as offsets (arena_offset). */
static int offsets(const pc_model *m, const pc_step *s, size_t n, long *off)
{
    size_t i;
    for (i = 0; i < n; i++)
        if (!arena_offset(m, s->io[i], &off[i]))
            return 0;
    return 1;
}

/* A binary float kernel in one of the layouts of one block (kernels.c), as operations. */
static int print_binary(const pc_model *m, const pc_step *s, int code, int layout)
{
    const pc_bcast *q = (const pc_bcast *)s->prm;
    long x[3], lo = 0;
    size_t i, r, k;
    if (layout > PC_COL_B || !offsets(m, s, 3, x))
        return 0;
    printf("elements %s\n", kernel_name(s->fn));
    if (layout == PC_ROW_B || layout == PC_COL_B) {
        for (r = 0; r < q->d[4]; r++)
            for (k = 0; k < q->d[5]; k++) {
                const long e = (long)(4 * (r * q->d[5] + k));
                print_op(&lo, code, x[0] + e, x[1] + 4 * (long)(layout == PC_ROW_B ? k : r), 0, x[2] + e);
            }
    } else {
        for (i = 0; i < s->n; i++)
            print_op(&lo, code, x[0] + (layout == PC_SCALAR_A ? 0 : 4 * (long)i),
                     x[1] + (layout == PC_SCALAR_B ? 0 : 4 * (long)i), 0, x[2] + 4 * (long)i);
    }
    print_pool(m, lo);
    return 1;
}

static int print_unary(const pc_model *m, const pc_step *s, int code)
{
    long x[2], lo = 0;
    size_t i;
    if (!offsets(m, s, 2, x))
        return 0;
    printf("elements %s\n", kernel_name(s->fn));
    for (i = 0; i < s->n; i++)
        print_op(&lo, code, x[0] + 4 * (long)i, 0, 0, x[1] + 4 * (long)i);
    print_pool(m, lo);
    return 1;
}

/* Copies of 4-byte elements: contiguous, two-level strided, concatenated, gathered. */
static int print_copies(const pc_model *m, const pc_step *s)
{
    long x[PC_MAX_RANK + 2], lo = 0;
    size_t i, j, k;
    if (s->fn == k_copy_4 || s->fn == k_strided2_4) {
        const pc_strided *q = (const pc_strided *)s->prm;
        const int flat = s->fn == k_copy_4;
        const size_t rows = flat ? 1 : q->d[4], cols = flat ? s->n : q->d[5];
        if (!offsets(m, s, 2, x))
            return 0;
        printf("elements %s\n", kernel_name(s->fn));
        for (i = 0; i < rows; i++)
            for (j = 0; j < cols; j++)
                print_op(&lo, PC_SOP_COPY, x[0] + 4 * (q->base + (flat ? (long)j : (long)i * q->st[4] +
                                                                             (long)j * q->st[5])),
                         0, 0, x[1] + 4 * (long)(i * cols + j));
    } else if (s->fn == k_concat) {
        const pc_concat *q = (const pc_concat *)s->prm;
        long out;
        if (q->esize != 4 || q->n_in > PC_MAX_RANK + 1 || !offsets(m, s, q->n_in + 1, x))
            return 0;
        printf("elements %s\n", kernel_name(s->fn));
        for (out = x[q->n_in], i = 0; i < q->outer; i++)
            for (k = 0; k < q->n_in; k++)
                for (j = 0; j < q->inner[k]; j++, out += 4)
                    print_op(&lo, PC_SOP_COPY, x[k] + 4 * (long)(i * q->inner[k] + j), 0, 0, out);
    } else if (s->fn == k_gather_cols_4) {
        const pc_gather *q = (const pc_gather *)s->prm;
        const int64_t *idx = (const int64_t *)s->io[1];
        if (!arena_offset(m, s->io[0], &x[0]) || !arena_offset(m, s->io[2], &x[2]) || q->inner != 1)
            return 0;
        printf("elements %s\n", kernel_name(s->fn));
        for (i = 0; i < q->outer; i++)
            for (j = 0; j < q->n_idx; j++)
                print_op(&lo, PC_SOP_COPY,
                         x[0] + 4 * (long)(i * q->len + (size_t)(idx[j] < 0 ? idx[j] + (int64_t)q->len : idx[j])),
                         0, 0, x[2] + 4 * (long)(i * q->n_idx + j));
    } else {
        return 0;
    }
    print_pool(m, lo);
    return 1;
}

/* A node's kernel whose work has the program form (element operations of its own
 * arithmetic, on the same elements in the same order), printed as a program; 0 prints
 * nothing. */
static int print_elements(const pc_model *m, const pc_step *s)
{
    int l;
#define BINARY_CASE(KERNEL, CODE, EXPR)                                                        \
    for (l = 0; l < PC_LAYOUTS; l++)                                                           \
        if (s->fn == KERNEL[l])                                                                \
            return print_binary(m, s, CODE, l);
#define UNARY_CASE(KERNEL, CODE, EXPR)                                                         \
    if (s->fn == KERNEL)                                                                       \
        return print_unary(m, s, CODE);
    PC_FLOAT_BINARY_OPS(BINARY_CASE)
    PC_FLOAT_UNARY_OPS(UNARY_CASE)
#undef BINARY_CASE
#undef UNARY_CASE
    return print_copies(m, s);
}

static int is_dense(pc_kernel_fn fn)
{
    return fn == k_gemm_chain || fn == k_gemm || fn == k_matmul || fn == pc_gemm_rows_kernels[0] ||
           fn == pc_gemm_rows_kernels[1];
}

/* The layers of a dense step (a chain, or one Gemm or MatMul), when each is of the form
 * printed; 0 prints nothing. */
static int print_dense(const pc_model *m, const pc_step *s)
{
    const pc_gemm_chain *chain = s->fn == k_gemm_chain ? (const pc_gemm_chain *)s->prm : NULL;
    const size_t n = chain ? chain->n_layers : 1;
    const int has_c = s->fn != k_matmul;
    size_t l;
    if (!is_dense(s->fn))
        return 0;
    for (l = 0; l < n; l++)
        if (!layer_ok(m, chain ? &chain->layer[l].g : (const pc_gemm *)s->prm, s->io + 4 * l, has_c))
            return 0;
    printf("dense %zu\n", n);
    for (l = 0; l < n; l++)
        print_layer(m, chain ? &chain->layer[l].g : (const pc_gemm *)s->prm, s->io + 4 * l, has_c);
    return 1;
}

/* The element operations by code: the float ones with their expression in a and b, from
 * the list the kernels are made of (formulas.h), the others by name. */
static void print_codes(void)
{
#define PRINT_SOP(KERNEL, CODE, EXPR) printf("sop %d %s %s\n", CODE, #CODE, #EXPR);
    PC_FLOAT_BINARY_OPS(PRINT_SOP)
    PC_FLOAT_UNARY_OPS(PRINT_SOP)
#undef PRINT_SOP
#define PRINT_NAME(CODE) printf("sop %d %s\n", CODE, #CODE);
    PRINT_NAME(PC_SOP_EQ) PRINT_NAME(PC_SOP_GT) PRINT_NAME(PC_SOP_GE) PRINT_NAME(PC_SOP_LT)
    PRINT_NAME(PC_SOP_LE) PRINT_NAME(PC_SOP_WHERE) PRINT_NAME(PC_SOP_COPY)
    PRINT_NAME(PC_SOP_COPY1) PRINT_NAME(PC_SOP_DOT)
#undef PRINT_NAME
}

/* The name of a kernel the plan runs, for the message of a step without a C form. */
static const char *kernel_name(pc_kernel_fn fn)
{
    static const char *const layouts[PC_LAYOUTS] = {"same", "scalar_a", "scalar_b", "row_b",
                                                    "col_b", "general2", "general"};
    static char name[48];
    int l;
#define BINARY_NAME(KERNEL, CODE, EXPR)                                                        \
    for (l = 0; l < PC_LAYOUTS; l++)                                                           \
        if (fn == KERNEL[l]) {                                                                 \
            snprintf(name, sizeof name, "%s (layout %s)", #KERNEL, layouts[l]);                \
            return name;                                                                       \
        }
#define UNARY_NAME(KERNEL, CODE, EXPR)                                                         \
    if (fn == KERNEL)                                                                          \
        return #KERNEL;
#define NAME(KERNEL)                                                                           \
    if (fn == KERNEL)                                                                          \
        return #KERNEL;
    PC_FLOAT_BINARY_OPS(BINARY_NAME)
    PC_FLOAT_UNARY_OPS(UNARY_NAME)
    NAME(k_where_f_same) NAME(k_copy_4) NAME(k_strided2_4) NAME(k_concat) NAME(k_gather_cols_4)
    NAME(k_reduce_sum_last)
#undef BINARY_NAME
#undef UNARY_NAME
#undef NAME
    return "a node's own kernel";
}

static void print_checks(const pc_model *m)
{
    printf("checks lo=%08lx,%08lx,%08lx hi=%08lx,%08lx,%08lx reach_pos2=%08lx reach_cos2=%08lx span=",
           bits(m->lo[0]), bits(m->lo[1]), bits(m->lo[2]), bits(m->hi[0]), bits(m->hi[1]),
           bits(m->hi[2]), bits(m->reach_pos2), bits(m->reach_cos2));
    if (m->has_span)
        printf("%08lx,%08lx\n", bits(m->t_lo), bits(m->t_hi));
    else
        printf("-\n");
}

static void print_plan(const pc_model *m)
{
    const pc_plan *p = &m->plans[0];
    size_t k;
    print_codes();
    print_checks(m);
    printf("plan steps=%zu in=%ld t=", p->n_steps, offset_of(m, p->in));
    if (p->t)
        printf("%ld", offset_of(m, p->t));
    else
        printf("-");
    printf(" out=%ld\n", offset_of(m, p->out));
    for (k = 0; k < p->n_steps; k++) {
        const pc_step *s = &p->steps[k];
        printf("step %zu ", k);
        if (is_program(s->fn)) {
            printf("program\n");
            print_program16(m, (const pc_scalar_program16 *)s->prm);
        } else if (s->fn == k_scalar_program) {
            printf("program\n");
            print_program32(m, (const pc_scalar_program *)s->prm);
        } else if (!print_dense(m, s) && !print_elements(m, s)) {
            printf("kernel %s\n", kernel_name(s->fn));
        }
    }
}

#define USAGE "usage: %s MODEL.onnx [--allow-unbounded] [--allow-unsigned] > plan\n"

int main(int argc, char **argv)
{
    pc_options opts;
    pc_model *model;
    pc_error err;
    int i;
    if (argc < 2) {
        fprintf(stderr, USAGE, argv[0]);
        return 2;
    }
    if (!strcmp(argv[1], "-h") || !strcmp(argv[1], "--help")) {
        printf(USAGE, argv[0]);
        return 0;
    }
    memset(&opts, 0, sizeof opts);
    opts.max_batch = 1;
    /* The interpreter's entries, which list every operation: a compiled program keeps
     * only the offsets it reads and writes (kernels.h). Same programs either way. */
    opts.flags = PC_LOAD_INTERPRET;
    for (i = 2; i < argc; i++) {
        if (!strcmp(argv[i], "--allow-unbounded"))
            opts.flags |= PC_LOAD_ALLOW_UNBOUNDED;
        else if (!strcmp(argv[i], "--allow-unsigned"))
            opts.flags |= PC_LOAD_ALLOW_UNSIGNED;
        else {
            fprintf(stderr, "%s: unknown option %s\n", argv[0], argv[i]);
            return 2;
        }
    }
    if (pc_load_file(argv[1], &opts, &model, &err) != PC_OK) {
        fprintf(stderr, "posecorr-plan: %s: %s\n", argv[1], err.message);
        return 1;
    }
    print_plan(model);
    pc_free(model);
    return 0;
}
