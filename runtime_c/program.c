/* One-pose programs, compiled while the graph streams past:
 *
 * 1. a node whose prepare function gave an element map (op.h) is expanded into element
 *    operations: each output element becomes a reference to an operation, to a constant
 *    of the program's pool or to an element already in the arena; copies (slices,
 *    gathers, concatenations) cost nothing, operations on constants are computed now;
 * 2. when a node without an element form comes (or the program is full), the program
 *    closes: elements still needed get arena storage (the operation computing one writes
 *    it there), operations nothing needs are dropped, the rest are ordered by dependency
 *    level and code (one dispatch per group), their results kept in temporaries reused
 *    by liveness, and the program is one k_scalar_program step.
 *
 * Each element is computed by the same IEEE operations, in the same order, as the
 * kernels compute it, so results are bit-identical (tests/test_runtime_c.py compares the
 * 1-pose and 16-pose plans of every model). */
#include "program.h"

#include <stddef.h>
#include <string.h>
#ifdef PC_PRINT_SHAPES
/* Given by tools/print_shapes.c, the shape printer that tools/compile_programs.py runs:
 * one byte of a shape, then the end of it. */
void pc_print_shape_byte(unsigned byte);
void pc_print_shape_end(void);
#endif

/* A node with more output elements keeps its kernel: the loops win there. */
#define PC_PROGRAM_MAX_ELEMS 64
/* A matrix product with more multiply-adds keeps its (vectorised) kernel. */
#define PC_PROGRAM_MAX_MACS 128
/* Terms of one dot product (sums and matrix products); their operands are arrays on the
 * stack of the expansion, which a small target counts. */
#define PC_PROGRAM_MAX_TERMS 32
#define PC_PROGRAM_DEFAULT_OPS 512
/* Longest dot product an addition extends. */
#define PC_EXTEND_MAX_TERMS 8
/* The programs' constant pools of all plans together, so that their offsets (negative,
 * from the activations) fit the 16-bit entries. */
#define PC_KPOOL_MAX 8192

/* References to an element: >= 0 the result of an operation; below, an element of the
 * arena (kind 0: byte offset from the activations) or of the constant pool (kind 1). */
#define PC_EXT(x, kind) (-1 - (int32_t)((uint32_t)(x) << 1 | (uint32_t)(kind)))
#define PC_EXT_KIND(r) ((uint32_t)(-1 - (r)) & 1u)
#define PC_EXT_INDEX(r) ((uint32_t)(-1 - (r)) >> 1)
#define PC_ACT_REF(off) PC_EXT(off, 0)
#define PC_K_REF(k) PC_EXT(k, 1)
#define PC_IS_K(r) ((r) < 0 && PC_EXT_KIND(r) == 1)

#define PC_NO_DEST INT32_MIN
/* An entry that adds a b to the DOT before it. */
#define PC_TERM 0xff

/* What the close makes of an operation (pc_eop.state). */
enum { PC_DEAD = 0, PC_KEPT, PC_ORDERED, PC_STORED };

/* 24 bytes: the one-pose compiler's working memory is mostly these. */
typedef struct pc_eop {
    uint8_t code;       /* PC_SOP_*, or PC_TERM */
    uint8_t n_terms;    /* DOT: PC_TERM entries after it */
    uint16_t state;     /* close: PC_DEAD .. PC_STORED */
    int32_t a, b, c;
    int32_t out;        /* the arena offset of a needed element (PC_NO_DEST: none yet), or
                         * once ordered, its temporary's slot, then where the result goes */
    int32_t last;       /* close: its chain's length, then its last reader's position, then
                         * its own position */
} pc_eop;

/* An operation's index in the close's arrays: a program holds fewer than 4,100 operations
 * (cap_ops: beyond that its pool would pass PC_KPOOL_MAX, and pc_program_takes takes no
 * node). */
typedef uint16_t pc_opid;

/* Operations live in chunks on the keep end, taken as the program grows and given back
 * when it closes. */
#define PC_CHUNK_OPS 32

typedef struct pc_program pc_program;
struct pc_program {
    pc_eop **chunk;
    size_t n_chunks, n_ops, cap_ops;
    uint32_t **kchunk;  /* the constant pool, as bits, in chunks taken as it grows */
    size_t n_k, cap_k, n_kchunks;
    int32_t zero_k;     /* the sums' starting zero (pc_kzero), or -1 */
    int open;
    int interpret;      /* PC_LOAD_INTERPRET */
    pc_scratch_mark mark; /* keep end at opening: element maps above it */
    size_t pending;     /* elements of records with maps: copies a close may add */
};

#define PC_OP(g, i) ((g)->chunk[(size_t)(i) / PC_CHUNK_OPS][(size_t)(i) % PC_CHUNK_OPS])
#define PC_CHUNK_K 32
#define PC_KBITS(g, i) ((g)->kchunk[(size_t)(i) / PC_CHUNK_K][(size_t)(i) % PC_CHUNK_K])

static pc_status pc_program_full(pc_pass *pp)
{
    return pc_fail(pp->b->err, PC_ERR_MEMORY, "one-pose program over its limits");
}

pc_status pc_program_start(pc_pass *pp, const pc_program_limits *limits)
{
    pc_builder *b = pp->b;
    pc_program *g = pc_scratch_alloc(&b->scratch, PC_KEEP, sizeof *g);
    const size_t ops = limits && limits->ops ? limits->ops : PC_PROGRAM_DEFAULT_OPS;
    if (!g)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    g->cap_ops = (ops + PC_CHUNK_OPS - 1) / PC_CHUNK_OPS * PC_CHUNK_OPS;
    g->cap_k = g->cap_ops / 2 + 16;
    g->chunk = pc_scratch_alloc_raw(&b->scratch, PC_KEEP,
                                    g->cap_ops / PC_CHUNK_OPS * sizeof *g->chunk);
    g->kchunk = pc_scratch_alloc_raw(&b->scratch, PC_KEEP,
                                     (g->cap_k + PC_CHUNK_K - 1) / PC_CHUNK_K * sizeof *g->kchunk);
    if (!g->chunk || !g->kchunk)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory for one-pose programs "
                       "(pc_options.program_ops)");
    g->interpret = limits && limits->interpret;
    g->zero_k = -1;
    pp->prog = g;
    return PC_OK;
}

/* ---- what a program takes ------------------------------------------------------------ */

static int pc_element_type(int dtype)
{
    return dtype == PC_F32 || dtype == PC_BOOL;
}

/* Operations one output element of node p adds, at most. */
static size_t pc_element_ops(const pc_prep *p)
{
    switch (p->emap) {
    case PC_EMAP_SOP: return p->sop == PC_SOP_ADD ? PC_EXTEND_MAX_TERMS + 1 : 1;
    case PC_EMAP_SUM: return ((const pc_reduce *)p->prm)->d[5] + 1;
    case PC_EMAP_PRODUCT: return ((const pc_gemm *)p->prm)->K + 2;
    default: return 0;
    }
}

/* Operations node p adds, at most. */
static size_t pc_expansion_ops(const pc_prep *p)
{
    return p->out[0]->count * pc_element_ops(p);
}

/* Pool constants node p may add, at most: its constant operands' elements and what
 * operations on constants give. */
static size_t pc_k_bound(const pc_prep *p)
{
    const size_t n = p->out[0]->count;
    switch (p->emap) {
    case PC_EMAP_SOP: return 4 * n + 1;
    case PC_EMAP_SUM: return n * (((const pc_reduce *)p->prm)->d[5] + 1) + 2;
    case PC_EMAP_PRODUCT: return n * (2 * ((const pc_gemm *)p->prm)->K + 2) + 1;
    default: return n;
    }
}

int pc_program_takes(const pc_pass *pp, const pc_prep *p)
{
    size_t j;
    const pc_value *o;
    if (!pp->prog || pp->batch != 1 || p->emap == PC_EMAP_NONE || p->alias_of >= 0 ||
        p->n_out != 1 || !p->out[0] ||
        pp->region[PC_REGION_KPOOL].used + 4 * pp->prog->cap_k > PC_KPOOL_MAX)
        return 0;
    o = p->out[0];
    if (o->count == 0 || o->count > PC_PROGRAM_MAX_ELEMS || !pc_element_type(o->dtype))
        return 0;
    for (j = 0; j < p->n_in; j++) {
        const pc_value *v = p->in[j];
        if (!v)
            continue;
        if (!pc_element_type(v->dtype) && !(p->emap == PC_EMAP_SELECT && v->cdata))
            return 0;
        if (v->count * pc_dtype_size(v->dtype) > 0x3fffffff)
            return 0;
    }
    if (p->emap == PC_EMAP_SUM) {
        const size_t len = ((const pc_reduce *)p->prm)->d[5];
        if (len == 0 || len > PC_PROGRAM_MAX_TERMS)
            return 0;
    }
    if (p->emap == PC_EMAP_PRODUCT) {
        const pc_gemm *q = (const pc_gemm *)p->prm;
        for (j = 0; j < q->nbd; j++) /* batch dimensions of one pose are 1 */
            if (q->bd[j] != 1)
                return 0;
        if (q->K == 0 || q->K > PC_PROGRAM_MAX_TERMS || o->count * q->K > PC_PROGRAM_MAX_MACS)
            return 0;
    }
    /* An MLP layer runs in the dense chain: 8 lanes a row there (AVX2) or sums kept in
     * registers (a load, a multiply and an add a multiply-add), where the interpreter
     * spends about ten instructions a multiply-add; left out, it also leaves the programs
     * beside it the shapes of the shipped models' encoders and decoders, whose compiled
     * forms match whatever the hidden widths. The exception is a linear map, without a
     * kernel of its K and N, of values the open program computes (PMC's features to the
     * correction): leaving would split that program in two. */
    if (p->layer) {
        const int avx2 = p->fn == pc_gemm_rows_kernels[1] &&
                         pc_gemm_rows_kernels[1] != pc_gemm_rows_kernels[0];
        const char *why;
        pc_chain_layer_fn((const pc_gemm *)p->prm, avx2, &why);
        if (!avx2 || !*why || ((const pc_gemm *)p->prm)->act != PC_ACT_NONE ||
            !p->in[0] || !p->in[0]->elems)
            return 0;
    }
    /* what one node may add: operations, copies at the close, pool constants */
    return pc_expansion_ops(p) + o->count <= pp->prog->cap_ops / 2 &&
           pc_k_bound(p) <= pp->prog->cap_k;
}

/* ---- element references --------------------------------------------------------------- */

/* A new pool constant; its index in *i. */
static pc_status pc_k_push(pc_pass *pp, uint32_t bits, size_t *i)
{
    pc_program *g = pp->prog;
    if (g->n_k == g->cap_k)
        return pc_program_full(pp);
    if (g->n_k == g->n_kchunks * PC_CHUNK_K) {
        uint32_t *c = pc_scratch_alloc_raw(&pp->b->scratch, PC_KEEP, PC_CHUNK_K * sizeof *c);
        if (!c)
            return pc_fail(pp->b->err, PC_ERR_MEMORY, "out of memory for a one-pose program "
                           "(pc_options.program_ops, PC_LOAD_NO_PROGRAMS)");
        g->kchunk[g->n_kchunks++] = c;
    }
    PC_KBITS(g, g->n_k) = bits;
    *i = g->n_k++;
    return PC_OK;
}

static pc_status pc_k(pc_pass *pp, uint32_t bits, int32_t *r)
{
    pc_program *g = pp->prog;
    size_t i;
    pc_status st;
    for (i = 0; i < g->n_k; i++)
        if (PC_KBITS(g, i) == bits && (int32_t)i != g->zero_k) {
            *r = PC_K_REF(i);
            return PC_OK;
        }
    if ((st = pc_k_push(pp, bits, &i)) != PC_OK)
        return st;
    *r = PC_K_REF(i);
    return PC_OK;
}

/* The zero a sum starts from, in a slot of its own: the shape tells it from a model's zero,
 * so that compiled code may start a sum of squares at its first square (exact: a square is
 * never -0, and 0 + x is x for every other x). */
static pc_status pc_kzero(pc_pass *pp, int32_t *r)
{
    pc_program *g = pp->prog;
    size_t i;
    pc_status st;
    if (g->zero_k < 0) {
        if ((st = pc_k_push(pp, 0, &i)) != PC_OK)
            return st;
        g->zero_k = (int32_t)i;
    }
    *r = PC_K_REF(g->zero_k);
    return PC_OK;
}

static pc_status pc_kf(pc_pass *pp, float x, int32_t *r)
{
    uint32_t bits;
    memcpy(&bits, &x, 4);
    return pc_k(pp, bits, r);
}

static pc_status pc_elem(pc_pass *pp, const pc_value *v, size_t e, int32_t *r)
{
    if (v->elems) {
        *r = v->elems[e];
        return PC_OK;
    }
    if (v->cdata) {
        uint32_t bits = 0;
        if (v->dtype == PC_BOOL)
            bits = ((const uint8_t *)v->cdata)[e];
        else
            memcpy(&bits, (const uint8_t *)v->cdata + 4 * e, 4);
        return pc_k(pp, bits, r);
    }
    *r = PC_ACT_REF(pp->blocks[v->block].off + e * pc_dtype_size(v->dtype));
    return PC_OK;
}

/* Element of `in` that broadcasting reads for element e of `out` (numpy rules). */
static size_t pc_bcast_element(const pc_value *in, const pc_value *out, size_t e)
{
    size_t idx = 0, stride = 1;
    int k;
    for (k = 0; k < out->rank; k++) {
        const int dk = out->rank - 1 - k, ik = in->rank - 1 - k;
        const size_t od = (size_t)out->dims[dk], coord = e % od;
        e /= od;
        if (ik >= 0) {
            const size_t id = (size_t)in->dims[ik];
            idx += (id == 1 ? 0 : coord) * stride;
            stride *= id;
        }
    }
    return idx;
}

/* Room for n more operations: chunks taken now, so that adding one cannot fail. */
static pc_status pc_reserve(pc_pass *pp, size_t n)
{
    pc_program *g = pp->prog;
    if (g->n_ops + n > g->cap_ops)
        return pc_program_full(pp);
    while (g->n_chunks * PC_CHUNK_OPS < g->n_ops + n) {
        pc_eop *c = pc_scratch_alloc_raw(&pp->b->scratch, PC_KEEP, PC_CHUNK_OPS * sizeof *c);
        if (!c)
            return pc_fail(pp->b->err, PC_ERR_MEMORY, "out of memory for a one-pose program "
                           "(pc_options.program_ops, PC_LOAD_NO_PROGRAMS)");
        g->chunk[g->n_chunks++] = c;
    }
    return PC_OK;
}

/* Callers have reserved the room (pc_reserve). */
static int32_t pc_new_op(pc_program *g, int code, int32_t a, int32_t b, int32_t c)
{
    pc_eop *op = &PC_OP(g, g->n_ops);
    memset(op, 0, sizeof *op);
    op->code = (uint8_t)code;
    op->a = a;
    op->b = b;
    op->c = c;
    op->out = PC_NO_DEST;
    return (int32_t)g->n_ops++;
}

static float pc_kval(const pc_program *g, int32_t r)
{
    float x;
    memcpy(&x, &PC_KBITS(g, PC_EXT_INDEX(r)), 4);
    return x;
}

/* An element operation, computed now when its operands are constants. */
/* A dot product that an addition may extend (the extended one is a new operation: the
 * old one stays for its other readers, or goes as dead). */
static int pc_extendable(const pc_program *g, int32_t r)
{
    return r >= 0 && PC_OP(g, r).code == PC_SOP_DOT &&
           PC_OP(g, r).n_terms + 2 <= PC_EXTEND_MAX_TERMS;
}

static int pc_is_mul(const pc_program *g, int32_t r)
{
    return r >= 0 && PC_OP(g, r).code == PC_SOP_MUL;
}

/* x + y as a dot product, when one side is one: (c + sum) + y is the dot product with one
 * more term (y's product when y is a multiplication, else y x 1, exact), and x + a b is
 * the one-term product with c = x. IEEE addition commutes, so either side may be the dot
 * product; the sums stay in the kernels' order. Returns -1 when neither applies. */
static int32_t pc_add_as_dot(pc_pass *pp, int32_t x, int32_t y)
{
    pc_program *g = pp->prog;
    int32_t d, one, r;
    uint32_t t, n;
    if (!pc_extendable(g, x) && pc_extendable(g, y)) {
        d = x;
        x = y;
        y = d;
    }
    if (pc_extendable(g, x)) {
        if (!pc_is_mul(g, y) && pc_kf(pp, 1.0f, &one) != PC_OK)
            return -1;
        n = PC_OP(g, x).n_terms;
        r = pc_new_op(g, PC_SOP_DOT, PC_OP(g, x).a, PC_OP(g, x).b, PC_OP(g, x).c);
        for (t = 1; t <= n; t++)
            pc_new_op(g, PC_TERM, PC_OP(g, x + (int32_t)t).a, PC_OP(g, x + (int32_t)t).b, 0);
        if (pc_is_mul(g, y))
            pc_new_op(g, PC_TERM, PC_OP(g, y).a, PC_OP(g, y).b, 0);
        else
            pc_new_op(g, PC_TERM, y, one, 0);
        PC_OP(g, r).n_terms = (uint8_t)(n + 1);
        return r;
    }
    if (!pc_is_mul(g, y) && pc_is_mul(g, x)) {
        d = x;
        x = y;
        y = d;
    }
    if (pc_is_mul(g, y))
        return pc_new_op(g, PC_SOP_DOT, PC_OP(g, y).a, PC_OP(g, y).b, x);
    return -1;
}

/* An element operation, computed now when its operands are constants. */
static pc_status pc_sop(pc_pass *pp, int code, int32_t a, int32_t b, int32_t c, int32_t *r)
{
    pc_program *g = pp->prog;
    const int binary = PC_SOP_IS_BINARY(code), where = code == PC_SOP_WHERE;
    if (where && PC_IS_K(c)) {
        *r = PC_KBITS(g, PC_EXT_INDEX(c)) ? a : b;
        return PC_OK;
    }
    if (PC_IS_K(a) && (!(binary || where) || PC_IS_K(b)) && (!where || PC_IS_K(c)))
        return pc_k(pp, pc_sop_eval(code, PC_KBITS(g, PC_EXT_INDEX(a)),
                                    binary || where ? PC_KBITS(g, PC_EXT_INDEX(b)) : 0,
                                    where ? PC_KBITS(g, PC_EXT_INDEX(c)) : 0), r);
    if (code == PC_SOP_ADD && (*r = pc_add_as_dot(pp, a, b)) >= 0)
        return PC_OK;
    *r = pc_new_op(g, code, a, binary || where ? b : 0, where ? c : 0);
    return PC_OK;
}

/* c + sum of a[t] b[t], in order (the kernels' order); computed now over constants. */
static pc_status pc_dot(pc_pass *pp, int32_t c, const int32_t *a, const int32_t *b, size_t n,
                        int32_t *r)
{
    pc_program *g = pp->prog;
    size_t t;
    int all_k = PC_IS_K(c);
    for (t = 0; t < n && all_k; t++)
        all_k = PC_IS_K(a[t]) && PC_IS_K(b[t]);
    if (all_k) {
        float acc = pc_kval(g, c);
        for (t = 0; t < n; t++)
            acc += pc_kval(g, a[t]) * pc_kval(g, b[t]);
        return pc_kf(pp, acc, r);
    }
    *r = pc_new_op(g, PC_SOP_DOT, a[0], b[0], c);
    PC_OP(g, *r).n_terms = (uint8_t)(n - 1);
    for (t = 1; t < n; t++)
        pc_new_op(g, PC_TERM, a[t], b[t], 0);
    return PC_OK;
}

/* ---- expansion -------------------------------------------------------------------------- */

/* Element e of a sum over the last axis: one dot entry, each summand times 1 (exact: the
 * kernel's plain sum) or, a product summed, its own term. */
static pc_status pc_expand_sum(pc_pass *pp, const pc_prep *p, size_t e, int32_t *r)
{
    const size_t len = ((const pc_reduce *)p->prm)->d[5];
    int32_t ta[PC_PROGRAM_MAX_TERMS], tb[PC_PROGRAM_MAX_TERMS], zero, one;
    size_t k;
    pc_status st;
    if ((st = pc_kzero(pp, &zero)) != PC_OK || (st = pc_kf(pp, 1.0f, &one)) != PC_OK)
        return st;
    for (k = 0; k < len; k++) {
        if ((st = pc_elem(pp, p->in[0], e * len + k, &ta[k])) != PC_OK)
            return st;
        tb[k] = one;
        if (pc_is_mul(pp->prog, ta[k])) {
            tb[k] = PC_OP(pp->prog, ta[k]).b;
            ta[k] = PC_OP(pp->prog, ta[k]).a;
        }
    }
    return pc_dot(pp, zero, ta, tb, len, r);
}

/* Element e of a Gemm or MatMul: C's element (or 0), the dot over K, the activation. */
static pc_status pc_expand_product(pc_pass *pp, const pc_prep *p, size_t e, int32_t *r)
{
    const pc_gemm *q = (const pc_gemm *)p->prm;
    const size_t i = e / q->N, n = e % q->N;
    int32_t ta[PC_PROGRAM_MAX_TERMS], tb[PC_PROGRAM_MAX_TERMS], c, dot;
    size_t k;
    pc_status st;
    if (q->c_mode == 0) {
        st = pc_kzero(pp, &c);
    } else {
        const size_t ci = q->c_mode == 1 ? 0 : q->c_mode == 2 ? n : q->c_mode == 3 ? i
                                                                               : i * q->N + n;
        st = pc_elem(pp, p->in[2], ci, &c);
    }
    if (st != PC_OK)
        return st;
    for (k = 0; k < q->K; k++)
        if ((st = pc_elem(pp, p->in[0], i * q->a_rs + k * q->a_cs, &ta[k])) != PC_OK ||
            (st = pc_elem(pp, p->in[1], k * q->b_rs + n * q->b_cs, &tb[k])) != PC_OK)
            return st;
    if ((st = pc_dot(pp, c, ta, tb, q->K, &dot)) != PC_OK)
        return st;
    switch (q->act) {
    case PC_ACT_TANH: return pc_sop(pp, PC_SOP_TANH, dot, 0, 0, r);
    case PC_ACT_SIGMOID: return pc_sop(pp, PC_SOP_SIGMOID, dot, 0, 0, r);
    case PC_ACT_RELU: return pc_sop(pp, PC_SOP_RELU, dot, 0, 0, r);
    case PC_ACT_RADBAS: /* as its nodes expand: Mul(x, x), Neg, Exp */
        if ((st = pc_sop(pp, PC_SOP_MUL, dot, dot, 0, &dot)) != PC_OK ||
            (st = pc_sop(pp, PC_SOP_NEG, dot, 0, 0, &dot)) != PC_OK)
            return st;
        return pc_sop(pp, PC_SOP_EXP, dot, 0, 0, r);
    default: *r = dot; return PC_OK;
    }
}

static pc_status pc_expand_element(pc_pass *pp, const pc_prep *p, size_t e, int32_t *r)
{
    const pc_value *o = p->out[0];
    int32_t x[3] = {0, 0, 0};
    size_t j;
    pc_status st;
    switch (p->emap) {
    case PC_EMAP_SOP: {
        /* Where's operands are (cond, then, else); the entry reads c ? a : b. */
        const int where = p->sop == PC_SOP_WHERE;
        for (j = 0; j < p->n_in && j < 3; j++)
            if ((st = pc_elem(pp, p->in[j], pc_bcast_element(p->in[j], o, e), &x[j])) != PC_OK)
                return st;
        return where ? pc_sop(pp, p->sop, x[1], x[2], x[0], r) : pc_sop(pp, p->sop, x[0], x[1], 0, r);
    }
    case PC_EMAP_SELECT: {
        size_t input, elem;
        p->select(p, e, &input, &elem);
        return pc_elem(pp, p->in[input], elem, r);
    }
    case PC_EMAP_SUM: return pc_expand_sum(pp, p, e, r);
    case PC_EMAP_PRODUCT: return pc_expand_product(pp, p, e, r);
    default:
        return pc_fail(pp->b->err, PC_ERR_GRAPH, "no element form");
    }
}

/* Elements of the records with maps: the copies a close may have to add. */
static size_t pc_pending(const pc_pass *pp)
{
    size_t k, n = 0;
    for (k = 0; k < pp->b->cap_values; k++)
        if (pp->b->values[k].used && pp->b->values[k].elems)
            n += pp->b->values[k].count;
    return n;
}

pc_status pc_program_expand(pc_pass *pp, const pc_prep *p)
{
    pc_program *g = pp->prog;
    pc_value *o = p->out[0];
    size_t e;
    pc_status st;
    if (g->open)
        g->pending = pc_pending(pp);
    if (g->open && g->n_ops + pc_expansion_ops(p) + g->pending + o->count > g->cap_ops &&
        (st = pc_program_close(pp)) != PC_OK)
        return st;
    if (!g->open) {
        g->open = 1;
        g->n_ops = g->n_k = g->pending = g->n_chunks = g->n_kchunks = 0;
        g->zero_k = -1;
        g->mark = pc_scratch_save(&pp->b->scratch, PC_KEEP);
        pp->defer_frees = 1;
    }
    if (g->n_k + pc_k_bound(p) > g->cap_k) {
        if ((st = pc_program_close(pp)) != PC_OK)
            return st;
        return pc_program_expand(pp, p);
    }
    o->elems = pc_scratch_alloc_raw(&pp->b->scratch, PC_KEEP, o->count * sizeof(int32_t));
    if (!o->elems)
        return pc_fail(pp->b->err, PC_ERR_MEMORY, "out of memory");
    /* Room taken an element at a time: the bound of a whole node (an addition's, nine
     * operations an element) would hold chunks the program never fills. */
    for (e = 0; e < o->count; e++)
        if ((st = pc_reserve(pp, pc_element_ops(p))) != PC_OK ||
            (st = pc_expand_element(pp, p, e, &o->elems[e])) != PC_OK)
            return st;
    return PC_OK;
}

/* ---- closing ------------------------------------------------------------------------------ */

/* Needed elements get a block; the operation computing one writes it there, anything
 * else (a constant, an input element, a result already written elsewhere) is copied. */
static pc_status pc_materialize(pc_pass *pp)
{
    pc_builder *b = pp->b;
    pc_program *g = pp->prog;
    size_t i, e;
    pc_status st;
    if ((st = pc_reserve(pp, pc_pending(pp))) != PC_OK)
        return st;
    for (i = 0; i < b->cap_values; i++) {
        pc_value *v = &b->values[i];
        size_t esize;
        if (!v->used || !v->elems)
            continue;
        if ((st = pc_give_block(pp, (int32_t)i)) != PC_OK)
            return st;
        esize = pc_dtype_size(v->dtype);
        for (e = 0; e < v->count; e++) {
            const int32_t dest = (int32_t)(pp->blocks[v->block].off + e * esize);
            const int32_t r = v->elems[e];
            if (r >= 0 && PC_OP(g, r).out == PC_NO_DEST) {
                PC_OP(g, r).out = dest;
            } else {
                const int32_t copy = pc_new_op(g, esize == 1 ? PC_SOP_COPY1 : PC_SOP_COPY, r, 0, 0);
                PC_OP(g, copy).out = dest;
            }
        }
        v->elems = NULL;
    }
    return PC_OK;
}

/* Calls f(g, r) for every operand of the operation at i (its terms' included). */
#define PC_FOR_OPERANDS(g, i, STMT)                                                               \
    do {                                                                                         \
        const pc_eop *op_ = &PC_OP(g, i);                                                        \
        const int code_ = op_->code;                                                             \
        size_t t_;                                                                               \
        int32_t r;                                                                               \
        r = op_->a;                                                                              \
        STMT;                                                                                    \
        if (PC_SOP_IS_BINARY(code_) || code_ == PC_SOP_WHERE || code_ == PC_SOP_DOT) {           \
            r = op_->b;                                                                          \
            STMT;                                                                                \
        }                                                                                        \
        if (code_ == PC_SOP_WHERE || code_ == PC_SOP_DOT) {                                      \
            r = op_->c;                                                                          \
            STMT;                                                                                \
        }                                                                                        \
        for (t_ = 1; code_ == PC_SOP_DOT && t_ <= op_->n_terms; t_++) {                          \
            r = PC_OP(g, (i) + t_).a;                                                            \
            STMT;                                                                                \
            r = PC_OP(g, (i) + t_).b;                                                            \
            STMT;                                                                                \
        }                                                                                        \
    } while (0)

/* Operations whose result is needed, walking back from the stored ones (out = 1). */
static void pc_keep_needed(pc_program *g)
{
    size_t i;
    for (i = 0; i < g->n_ops; i++)
        PC_OP(g, i).state = PC_OP(g, i).out != PC_NO_DEST ? PC_KEPT : PC_DEAD;
    for (i = g->n_ops; i-- > 0;) {
        if (!PC_OP(g, i).state || PC_OP(g, i).code == PC_TERM)
            continue;
        PC_FOR_OPERANDS(g, i, if (r >= 0) PC_OP(g, r).state = PC_KEPT);
    }
}

static int pc_unit(const pc_program *g, size_t i)
{
    return PC_OP(g, i).state && PC_OP(g, i).code != PC_TERM;
}

/* Each kept operation's chain length (last): 1 plus its longest reader's. Readers come
 * after what they read, so walking back, an operation's length is final when reached and
 * it passes it on to its operands. */
static size_t pc_chains(pc_program *g)
{
    size_t i, n_units = 0;
    for (i = 0; i < g->n_ops; i++)
        PC_OP(g, i).last = 1;
    for (i = g->n_ops; i-- > 0;) {
        int32_t h;
        if (!pc_unit(g, i))
            continue;
        n_units++;
        h = PC_OP(g, i).last + 1;
        PC_FOR_OPERANDS(g, i, if (r >= 0 && PC_OP(g, r).last < h) PC_OP(g, r).last = h);
    }
    return n_units;
}

/* A kept operation not yet ordered (PC_KEPT) whose operands all are (PC_ORDERED). */
static int pc_ready(const pc_program *g, size_t i)
{
    int ready = pc_unit(g, i) && PC_OP(g, i).state == PC_KEPT;
    if (ready)
        PC_FOR_OPERANDS(g, i, if (r >= 0 && PC_OP(g, r).state != PC_ORDERED) ready = 0);
    return ready;
}

/* The ready operation to run next: one of the current code, else the one heading the
 * longest chain; -1 when none is ready. */
static int pc_next_ready(const pc_program *g, int cur)
{
    const size_t n_ops = g->n_ops;
    size_t i;
    int best = -1;
    for (i = 0; i < n_ops; i++)
        if (PC_OP(g, i).code == cur && pc_ready(g, i))
            return (int)i;
    for (i = 0; i < n_ops; i++)
        if (pc_ready(g, i) && (best < 0 || PC_OP(g, i).last > PC_OP(g, (size_t)best).last))
            best = (int)i;
    return best;
}

/* The kept operations (not terms) in an order that runs as few groups of one code as it
 * can: all ready operations of the current code run, and those they make ready, before
 * the code changes; the next code is that of the ready operation heading the longest
 * chain. No reader lists: readiness is asked of the operands, which keeps the close's
 * working memory to the order. */
static pc_status pc_order(pc_pass *pp, pc_opid **order_out, size_t *n_out)
{
    pc_program *g = pp->prog;
    const size_t n_ops = g->n_ops;
    pc_opid *order = pc_scratch_alloc_raw(&pp->b->scratch, PC_WORK, (n_ops + 1) * sizeof *order);
    const size_t n_units = pc_chains(g);
    size_t done = 0, i;
    if (!order)
        return pc_fail(pp->b->err, PC_ERR_MEMORY, "out of memory");
    while (done < n_units) {
        const int best = pc_next_ready(g, done ? PC_OP(g, (size_t)order[done - 1]).code : -1);
        int progress = 1, cur;
        if (best < 0)
            return pc_fail(pp->b->err, PC_ERR_GRAPH, "one-pose program has a cycle");
        cur = PC_OP(g, (size_t)best).code;
        while (progress) {
            progress = 0;
            for (i = 0; i < n_ops; i++) {
                if (PC_OP(g, i).code != cur || !pc_ready(g, i))
                    continue;
                PC_OP(g, i).state = PC_ORDERED;
                order[done++] = (pc_opid)i;
                progress = 1;
            }
        }
    }
    *order_out = order;
    *n_out = n_units;
    return PC_OK;
}

/* Temporaries of the results not stored: 4-byte slots reused once their last reader
 * has run. Returns the slot count. */
static pc_status pc_temps(pc_pass *pp, const pc_opid *order, size_t n, size_t *n_slots)
{
    pc_program *g = pp->prog;
    pc_opid *slot_free_at = pc_scratch_alloc_raw(&pp->b->scratch, PC_WORK, (n + 1) * sizeof *slot_free_at);
    size_t pos, slots = 0, s;
    if (!slot_free_at)
        return pc_fail(pp->b->err, PC_ERR_MEMORY, "out of memory");
    for (pos = 0; pos < n; pos++)
        PC_OP(g, order[pos]).last = -1;
    for (pos = 0; pos < n; pos++)
        PC_FOR_OPERANDS(g, (size_t)order[pos], if (r >= 0) PC_OP(g, r).last = (int32_t)pos);
    for (pos = 0; pos < n; pos++) {
        pc_eop *x = &PC_OP(g, order[pos]);
        if (x->out != PC_NO_DEST) {
            x->state = PC_STORED;
            continue;
        }
        /* A slot whose last reader ran before this operation is free again. */
        for (s = 0; s < slots && slot_free_at[s] >= pos; s++)
            ;
        if (s == slots)
            slots++;
        slot_free_at[s] = (pc_opid)x->last; /* read, so >= 0 */
        x->out = (int32_t)s; /* slot for now; an offset once the block is placed */
    }
    *n_slots = slots;
    return PC_OK;
}

/* The operand as the kernel reads it: a byte offset from the activations. */
static int32_t pc_operand(const pc_pass *pp, int32_t r, int32_t kpool_off)
{
    if (r >= 0)
        return PC_OP(pp->prog, r).out;
    if (PC_EXT_KIND(r) == 1)
        return kpool_off + 4 * (int32_t)PC_EXT_INDEX(r);
    return (int32_t)PC_EXT_INDEX(r);
}

/* Entry k of a program of either width. */
static void pc_put(void *ops, int wide, size_t k, int32_t a, int32_t b, int32_t c, int32_t o)
{
    if (wide) {
        pc_scalar_op *e = (pc_scalar_op *)ops + k;
        e->a = a;
        e->b = b;
        e->c = c;
        e->o = o;
    } else {
        pc_scalar_op16 *e = (pc_scalar_op16 *)ops + k;
        e->a = (int16_t)a;
        e->b = (int16_t)b;
        e->c = (int16_t)c;
        e->o = (int16_t)(o == PC_DOT_TERM ? PC_DOT_TERM16 : o);
    }
}

#ifndef PC_NO_COMPILED_PROGRAMS
/* ---- compiled programs ----------------------------------------------------------------- */

/* A program's shape: for each operation in order its code, its term count, whether its
 * result is stored, and for each operand how many operations back it was computed (0:
 * read from the arena; 254: a constant; 253: a sum's starting zero (pc_kzero); 255, then
 * two bytes, when 253 or farther). Offsets and values are not part of it: a compiled
 * program's parameters are only what it reads from memory (pc_compiled_params), and it
 * keeps in registers what the shape says it computed itself. Equal shapes are the same
 * computation. */
typedef struct pc_shape_walk {
    uint64_t hash;               /* FNV-1a of the bytes */
    size_t len;
    size_t n_k;                  /* constant operands */
    size_t n_x;                  /* arena operands and stored results */
    const uint8_t *expect;       /* compare against these (len bytes known to match in size) */
    int differs;
    int print;
} pc_shape_walk;

static void pc_shape_byte(pc_shape_walk *w, unsigned byte)
{
    if (w->expect && w->expect[w->len] != byte)
        w->differs = 1;
#ifdef PC_PRINT_SHAPES
    if (w->print)
        pc_print_shape_byte(byte & 0xffu);
#endif
    w->hash = (w->hash ^ (byte & 0xffu)) * 0x100000001b3ull;
    w->len++;
}

static void pc_shape_ref(pc_shape_walk *w, const pc_program *g, int32_t r, size_t pos)
{
    size_t back;
    if (r < 0) {
        w->n_k += PC_IS_K(r);
        w->n_x += !PC_IS_K(r);
        pc_shape_byte(w, !PC_IS_K(r) ? 0 : (int32_t)PC_EXT_INDEX(r) == g->zero_k ? 253 : 254);
        return;
    }
    back = pos - (size_t)PC_OP(g, r).last; /* last holds an ordered operation's position here */
    if (back < 253) {
        pc_shape_byte(w, (unsigned)back);
    } else {
        pc_shape_byte(w, 255);
        pc_shape_byte(w, (unsigned)(back & 0xff));
        pc_shape_byte(w, (unsigned)(back >> 8));
    }
}

static void pc_shape(const pc_program *g, const pc_opid *order, size_t n, pc_shape_walk *w)
{
    size_t pos;
    w->hash = 0xcbf29ce484222325ull;
    w->len = 0;
    w->n_k = w->n_x = 0;
    w->differs = 0;
    for (pos = 0; pos < n; pos++) {
        const size_t i = (size_t)order[pos];
        const pc_eop *x = &PC_OP(g, i);
        pc_shape_byte(w, x->code);
        pc_shape_byte(w, x->code == PC_SOP_DOT ? x->n_terms : 0);
        pc_shape_byte(w, x->state == PC_STORED);
        w->n_x += x->state == PC_STORED;
        PC_FOR_OPERANDS(g, i, pc_shape_ref(w, g, r, pos));
    }
}

/* The compiled kernel of this program's shape (16-bit offsets), or NULL; *n_k: the
 * constants it reads, *n_x: its offsets. print: print the shape (PC_PRINT_SHAPES; once,
 * in the write pass). */
static pc_kernel_fn pc_compiled_kernel(pc_program *g, const pc_opid *order, size_t n,
                                       int print, size_t *n_k, size_t *n_x)
{
    pc_shape_walk w;
    size_t pos, k;
    *n_k = *n_x = 0;
    if (g->interpret || n > UINT16_MAX)
        return NULL;
    for (pos = 0; pos < n; pos++)
        PC_OP(g, order[pos]).last = (int32_t)pos;
    w.expect = NULL;
    w.print = print;
#ifdef PC_PRINT_SHAPES
    if (print) {
        pc_shape(g, order, n, &w);
        pc_print_shape_end();
    }
#endif
    w.print = 0;
    pc_shape(g, order, n, &w);
    for (k = 0; k < pc_n_compiled_programs; k++) {
        const pc_compiled_program *c = &pc_compiled_programs[k];
        if (c->n_bytes != w.len || c->hash != w.hash)
            continue;
        w.expect = c->shape;
        pc_shape(g, order, n, &w);
        if (!w.differs) {
            *n_k = w.n_k;
            *n_x = w.n_x;
            return c->fn;
        }
        w.expect = NULL;
    }
    return NULL;
}

/* A compiled program's parameters, in the order the shape lists them (kernels.h,
 * pc_compiled_program): the offsets of its arena operands and stored results (x), then
 * its constant operands (k). Nothing else: it keeps its own results in registers. */
static void pc_compiled_params(const pc_program *g, const pc_opid *order, size_t n, int16_t *x,
                               uint32_t *k)
{
    size_t pos;
    for (pos = 0; pos < n; pos++) {
        const pc_eop *op = &PC_OP(g, order[pos]);
        PC_FOR_OPERANDS(g, (size_t)order[pos], if (PC_IS_K(r)) *k++ = PC_KBITS(g, PC_EXT_INDEX(r));
                        else if (r < 0) *x++ = (int16_t)PC_EXT_INDEX(r));
        if (op->state == PC_STORED)
            *x++ = (int16_t)op->out;
    }
}

#endif

/* The program's entries (a header per group of one code, an entry per operation, one per
 * dot term), with the temporaries placed at `temp`; *hi: the largest activation offset
 * read or written, which decides the entries' width. */
static size_t pc_program_entries(pc_program *g, const pc_opid *order, size_t n, int32_t temp,
                                 int32_t *hi)
{
    size_t entries = 0, pos;
    int last_code = -1;
    *hi = 0;
    for (pos = 0; pos < n; pos++) {
        pc_eop *x = &PC_OP(g, order[pos]);
        if (x->state != PC_STORED)
            x->out = temp + 4 * x->out;
        entries += 1 + (x->code == PC_SOP_DOT ? x->n_terms : 0);
        if (x->code != last_code)
            entries++;
        last_code = x->code;
        if (x->out > *hi)
            *hi = x->out;
        PC_FOR_OPERANDS(g, (size_t)order[pos], if (r < 0 && PC_EXT_KIND(r) == 0 &&
                                                   (int32_t)PC_EXT_INDEX(r) > *hi) *hi =
                                                   (int32_t)PC_EXT_INDEX(r));
    }
    return entries;
}

/* The entries into ops, each group of one code behind its header (code, count). */
static void pc_program_write(pc_pass *pp, void *ops, int wide, const pc_opid *order, size_t n,
                             int32_t kpool_off)
{
    const pc_program *g = pp->prog;
    size_t pos, t, k = 0, header = 0, group = 0;
    int last_code = -1;
    for (pos = 0; pos < n; pos++) {
        const int32_t i = order[pos];
        const pc_eop *x = &PC_OP(g, i);
        const int binary = PC_SOP_IS_BINARY(x->code) || x->code == PC_SOP_WHERE ||
                           x->code == PC_SOP_DOT;
        const int ternary = x->code == PC_SOP_WHERE || x->code == PC_SOP_DOT;
        if (x->code != last_code) {
            if (last_code >= 0)
                pc_put(ops, wide, header, last_code, (int32_t)group, 0, 0);
            header = k++;
            group = 0;
            last_code = x->code;
        }
        pc_put(ops, wide, k++, pc_operand(pp, x->a, kpool_off),
               binary ? pc_operand(pp, x->b, kpool_off) : 0,
               ternary ? pc_operand(pp, x->c, kpool_off) : 0, x->out);
        group++;
        for (t = 1; x->code == PC_SOP_DOT && t <= x->n_terms; t++, group++)
            pc_put(ops, wide, k++, pc_operand(pp, PC_OP(g, i + t).a, kpool_off),
                   pc_operand(pp, PC_OP(g, i + t).b, kpool_off), 0, PC_DOT_TERM);
    }
    if (last_code >= 0)
        pc_put(ops, wide, header, last_code, (int32_t)group, 0, 0);
}

/* Writes the program (or, sizing pass, only takes its bytes). Both passes make the same
 * choices: offsets are the same in both, and the pool's are bounded (PC_KPOOL_MAX). */
static pc_status pc_emit_program(pc_pass *pp, const pc_opid *order, size_t n, int32_t temp)
{
    pc_program *g = pp->prog;
    size_t entries, n_k = 0, n_x = 0, size, k;
    int32_t kpool_off, hi;
    uint32_t *kpool;
    void *q, *ops;
    int wide;
    pc_step *s;
    void **io;
    pc_kernel_fn fn, compiled = NULL;
    /* The pool sits just below the activations: its entries are negative offsets. */
    kpool_off = (int32_t)pp->region[PC_REGION_KPOOL].used - (int32_t)pp->kpool_total;
    entries = pc_program_entries(g, order, n, temp, &hi);
    wide = hi > INT16_MAX;
    s = pc_region_take(pp, PC_REGION_STEPS, sizeof *s);
    io = pc_region_take(pp, PC_REGION_IO, 2 * sizeof(void *));
    fn = wide ? k_scalar_program : k_scalar_program16;
#ifndef PC_NO_COMPILED_PROGRAMS
    if (!wide && (compiled = pc_compiled_kernel(g, order, n, pp->fill, &n_k, &n_x)) != NULL)
        fn = compiled;
#endif
    /* The pool is the interpreter's: a compiled program reads its constants from its
     * parameters. Both passes decide alike, so the pool's offsets agree. */
    kpool = compiled ? NULL : pc_region_take(pp, PC_REGION_KPOOL, g->n_k * 4);
    for (k = 0; kpool && k < g->n_k; k++)
        kpool[k] = PC_KBITS(g, k);
    /* A compiled program's offsets, their count rounded up to even (its constants are
     * 4-byte words), or the interpreter's entries. */
    size = compiled ? (n_x + 1) / 2 * 2 * sizeof(int16_t)
           : wide   ? offsetof(pc_scalar_program, ops) + entries * sizeof(pc_scalar_op)
                    : offsetof(pc_scalar_program16, ops) + entries * sizeof(pc_scalar_op16);
    q = pc_region_take(pp, PC_REGION_PARAMS, size + n_k * sizeof(uint32_t));
    pp->n_steps++;
    pp->last_step = s;
    pp->last_layer = 0;
    if (!q)
        return PC_OK; /* sizing pass */
    s->fn = fn;
    s->io = io;
    s->prm = q;
    s->n = entries;
    io[0] = pp->act_base;
    io[1] = NULL;
#ifndef PC_NO_COMPILED_PROGRAMS
    if (compiled) {
        pc_compiled_params(g, order, n, (int16_t *)q, (uint32_t *)((char *)q + size));
        return PC_OK;
    }
#endif
    if (wide) {
        ((pc_scalar_program *)q)->n_ops = entries;
        ops = ((pc_scalar_program *)q)->ops;
    } else {
        ((pc_scalar_program16 *)q)->n_ops = entries;
        ops = ((pc_scalar_program16 *)q)->ops;
    }
    pc_program_write(pp, ops, wide, order, n, kpool_off);
    return PC_OK;
}

pc_status pc_program_close(pc_pass *pp)
{
    pc_program *g = pp->prog;
    pc_scratch_mark work;
    pc_opid *order = NULL;
    int32_t temp_block = -1;
    size_t n = 0, n_slots = 0;
    pc_status st;
    if (!g || !g->open)
        return PC_OK;
    work = pc_scratch_save(&pp->b->scratch, PC_WORK);
    if ((st = pc_materialize(pp)) != PC_OK)
        return st;
    pc_keep_needed(g);
    if ((st = pc_order(pp, &order, &n)) != PC_OK || (st = pc_temps(pp, order, n, &n_slots)) != PC_OK)
        return st;
    if (n_slots && (st = pc_block_new(pp, n_slots * 4, &temp_block)) != PC_OK)
        return st;
    if (n && (st = pc_emit_program(pp, order, n,
                                   temp_block >= 0 ? (int32_t)pp->blocks[temp_block].off : 0)) != PC_OK)
        return st;
    /* The program has run once its step has: what it read may be reused. */
    pp->defer_frees = 0;
    pc_block_unref(pp, temp_block);
    pc_block_flush(pp);
    g->open = 0;
    pc_scratch_restore(&pp->b->scratch, work);
    pc_scratch_restore(&pp->b->scratch, g->mark);
    return PC_OK;
}
