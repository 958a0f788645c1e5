/* One-pose programs. At N = 1 the exporter's quaternion, matrix and Gram-Schmidt
 * subgraphs are hundreds of steps over 1 to 9 elements, each costing more to launch
 * than to compute. Here each run of such steps becomes one k_scalar_program launch:
 *
 * 1. every step is expanded into element operations, in order: its sop (pc_prep.sop),
 *    the element map of its copy, gather or concatenation, or dot products for its
 *    last-axis sum or small matrix product (a sum of products absorbs the products);
 * 2. a copied element is renamed: later reads go to its source, so slices, gathers and
 *    concatenations cost nothing unless their result is read outside the run;
 * 3. operations whose result nothing reads are dropped (the zhou encoding uses 6 of the
 *    9 matrix entries it computes);
 * 4. the rest are ordered so that operations of one code run as a group (one dispatch),
 *    and their operands become byte offsets, bound to the arena when the plan is packed.
 *
 * Each element is computed by the same IEEE operations, in the same order, as the
 * kernels compute it, so results are bit-identical (tests/test_runtime_c.py compares
 * the 1-pose and 16-pose plans of every model, and pc_run with the hand-written zhou
 * function). */
#include "program.h"

#include <string.h>

/* A step with more output elements keeps its kernel: the loops win there. */
#define PC_PROGRAM_MAX_ELEMS 64
/* A matrix product with more multiply-adds keeps its (vectorised) kernel. */
#define PC_PROGRAM_MAX_MACS 128
/* Terms of one dot product (sums and matrix products). */
#define PC_PROGRAM_MAX_TERMS 64
/* Longest dot product an addition extends (the extended one is recomputed if it is also
 * read elsewhere). */
#define PC_EXTEND_MAX_TERMS 8
/* Operand references hold a 15-bit io slot and a 16-bit byte offset (PC_SOP_REF). */
#define PC_PROGRAM_MAX_SLOTS 4096
#define PC_PROGRAM_MAX_BYTES 0xffff

/* One element of a storage root, or of the program's constants k[] (v < 0). */
typedef struct pc_eref {
    int32_t v;
    uint32_t e;
} pc_eref;

#define PC_CONSTANT_V (-2)
#define PC_COPIED_TWICE (-3)
static const pc_eref pc_zero = {PC_CONSTANT_V, 0}, pc_one = {PC_CONSTANT_V, 1};

/* An element operation. DOT: o = c + sum of terms[t0, t0 + nt) (a, b pairs). */
typedef struct pc_eop {
    int code;
    pc_eref a, b, c, o;
    uint32_t t0, nt;
} pc_eop;

/* What the pass knows of one element of a root the run writes. */
typedef struct pc_elem {
    pc_eref renamed;    /* the source it copies (v < 0: not a copy) */
    pc_eref into;       /* the copy written in its place (v < 0: none; PC_COPIED_TWICE:
                         * copied twice, so written in place) */
    int32_t writer;     /* the last operation writing it, or -1 */
    uint8_t live;       /* read by a kept operation */
} pc_elem;

/* State of the pass: per root value id, reset between runs. */
typedef struct pc_prog {
    pc_builder *b;
    pc_eop *ops;
    size_t n_ops;
    pc_eref *terms;
    size_t n_terms;
    pc_elem **elem;     /* per root touched by the run: its elements' state, or NULL */
    uint8_t *outside;   /* root read after the run or a graph output */
    int32_t *slot_of;   /* root's io slot in the program being emitted, or -1 */
    int32_t *touched;   /* roots with state to reset */
    size_t n_touched;
} pc_prog;

/* Element of `in` that broadcasting reads for element e of `out` (numpy rules). */
static uint32_t pc_bcast_element(const pc_value *in, const pc_value *out, size_t e)
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
    return (uint32_t)idx;
}

/* A matrix product whose elements a program computes exactly as its kernel does
 * (pc_gemm_one, pc_gemm_rows): alpha 1, C absent or taken with beta 1. */
static int pc_small_product(const pc_draft *d)
{
    const pc_gemm *q = (const pc_gemm *)d->prm;
    if (d->fn != k_gemm && d->fn != k_matmul && d->fn != pc_gemm_rows_kernels[0] &&
        d->fn != pc_gemm_rows_kernels[1])
        return 0;
    if (q->K == 0 || q->K > PC_PROGRAM_MAX_TERMS || d->n * q->K > PC_PROGRAM_MAX_MACS)
        return 0;
    if (q->alpha != 1.0f || (q->c_mode != 0 && q->beta != 1.0f))
        return 0;
    return q->act == PC_ACT_NONE || q->act == PC_ACT_TANH || q->act == PC_ACT_SIGMOID ||
           q->act == PC_ACT_RELU;
}

/* Can draft d run as element operations? */
static int pc_expandable(const pc_builder *b, const pc_draft *d)
{
    uint32_t j;
    if (d->n == 0 || d->n > PC_PROGRAM_MAX_ELEMS)
        return 0;
    for (j = 0; j < d->n_io; j++) {
        const pc_value *v;
        if (d->io[j] < 0)
            return 0;
        v = &b->values[pc_root(b, d->io[j])];
        if (v->dtype != PC_F32 && v->dtype != PC_BOOL && !(v->dtype == PC_I64 && v->cdata))
            return 0;
        if (v->count * pc_dtype_size(v->dtype) > PC_PROGRAM_MAX_BYTES)
            return 0;
    }
    if (d->sop)
        return 1;
    if (d->fn == k_copy_4 || d->fn == k_strided2_4)
        return 1;
    if (d->fn == k_gather_cols_4)
        return b->values[pc_root(b, d->io[1])].cdata != NULL;
    if (d->fn == k_concat)
        return ((const pc_concat *)d->prm)->esize == 4;
    if (d->fn == k_reduce_sum_last) {
        const size_t len = ((const pc_reduce *)d->prm)->d[5];
        return len > 0 && len <= PC_PROGRAM_MAX_TERMS;
    }
    return pc_small_product(d);
}

/* Upper bounds of the operations and dot-product terms draft d expands to. */
static void pc_expansion_size(const pc_draft *d, size_t *ops, size_t *terms)
{
    *ops += d->n;
    if (d->sop == PC_SOP_ADD) {
        *terms += d->n * PC_EXTEND_MAX_TERMS;
    } else if (d->sop) {
        return;
    } else if (d->fn == k_reduce_sum_last) {
        *terms += d->n * ((const pc_reduce *)d->prm)->d[5];
    } else if (pc_small_product(d)) {
        *ops += d->n; /* the activation of each element */
        *terms += d->n * ((const pc_gemm *)d->prm)->K;
    }
}

static pc_status pc_touch(pc_prog *g, int32_t root)
{
    const size_t count = g->b->values[root].count;
    size_t e;
    if (g->elem[root])
        return PC_OK;
    /* one block per root: scratch rounds every allocation up to PC_ALIGN */
    g->elem[root] = pc_scratch_alloc_raw(&g->b->scratch, count * sizeof(pc_elem));
    if (!g->elem[root])
        return pc_fail(g->b->err, PC_ERR_MEMORY, "out of memory");
    for (e = 0; e < count; e++) {
        pc_elem *x = &g->elem[root][e];
        x->renamed.v = x->into.v = -1;
        x->renamed.e = x->into.e = 0;
        x->writer = -1;
        x->live = 0;
    }
    g->touched[g->n_touched++] = root;
    return PC_OK;
}

/* The operation that last wrote r in this run, or -1. */
static int32_t pc_writer(const pc_prog *g, pc_eref r)
{
    return r.v >= 0 && g->elem[r.v] ? g->elem[r.v][r.e].writer : -1;
}

/* Element e of value id, through the renames of earlier copies. */
static pc_eref pc_read(const pc_prog *g, int32_t id, size_t e)
{
    pc_eref r;
    r.v = pc_root(g->b, id);
    r.e = (uint32_t)e;
    if (g->elem[r.v] && g->elem[r.v][e].renamed.v >= 0)
        r = g->elem[r.v][e].renamed;
    return r;
}

static pc_status pc_emit(pc_prog *g, int code, pc_eref a, pc_eref b, pc_eref c, int32_t out,
                         size_t e)
{
    pc_eop *op = &g->ops[g->n_ops];
    pc_status st;
    op->code = code;
    op->a = a;
    op->b = b;
    op->c = c;
    op->o.v = pc_root(g->b, out);
    op->o.e = (uint32_t)e;
    op->t0 = op->nt = 0;
    if ((st = pc_touch(g, op->o.v)) != PC_OK)
        return st;
    if (code == PC_SOP_COPY)
        g->elem[op->o.v][e].renamed = a;
    g->elem[op->o.v][e].writer = (int32_t)g->n_ops++;
    return PC_OK;
}

static pc_status pc_emit_copy(pc_prog *g, int32_t in, size_t from, int32_t out, size_t to)
{
    const pc_eref a = pc_read(g, in, from);
    return pc_emit(g, PC_SOP_COPY, a, a, a, out, to);
}

/* Appends the term x (a product when a multiplication in this run made it, x 1 else). */
static void pc_add_sum_term(pc_prog *g, pc_eref x)
{
    const int32_t w = pc_writer(g, x);
    pc_eref *t = &g->terms[2 * g->n_terms++];
    if (w >= 0 && g->ops[w].code == PC_SOP_MUL) {
        t[0] = g->ops[w].a;
        t[1] = g->ops[w].b;
    } else {
        t[0] = x;
        t[1] = pc_one;
    }
}

/* o[e] = init + the terms appended since term t0. */
static pc_status pc_emit_dot(pc_prog *g, pc_eref init, size_t t0, int32_t out, size_t e)
{
    const pc_status st = pc_emit(g, PC_SOP_DOT, init, init, init, out, e);
    if (st != PC_OK)
        return st;
    g->ops[g->n_ops - 1].t0 = (uint32_t)t0;
    g->ops[g->n_ops - 1].nt = (uint32_t)(g->n_terms - t0);
    return PC_OK;
}

/* Appends the terms of dot product w to the terms under construction. */
static void pc_copy_terms(pc_prog *g, int32_t w)
{
    const pc_eop *dot = &g->ops[w];
    memmove(&g->terms[2 * g->n_terms], &g->terms[2 * dot->t0], 2 * dot->nt * sizeof(pc_eref));
    g->n_terms += dot->nt;
}

/* x + y kept in one dot product when a side is a product or a dot product of this run:
 * x + p q is the dot product (x; p q), and (c; t...) + y is (c; t..., y 1). Addition is
 * commutative bit for bit and y 1 = y exactly, so the result is the addition's. */
static pc_status pc_expand_add(pc_prog *g, pc_eref x, pc_eref y, int32_t out, size_t e)
{
    const int32_t wx = pc_writer(g, x), wy = pc_writer(g, y);
    const int dot_x = wx >= 0 && g->ops[wx].code == PC_SOP_DOT &&
                      g->ops[wx].nt < PC_EXTEND_MAX_TERMS;
    const int dot_y = wy >= 0 && g->ops[wy].code == PC_SOP_DOT &&
                      g->ops[wy].nt < PC_EXTEND_MAX_TERMS;
    const size_t t0 = g->n_terms;
    pc_eref init;
    if (dot_x || dot_y) {
        const int32_t w = dot_x ? wx : wy;
        init = g->ops[w].c;
        pc_copy_terms(g, w);
        pc_add_sum_term(g, dot_x ? y : x);
    } else if ((wy >= 0 && g->ops[wy].code == PC_SOP_MUL) ||
               (wx >= 0 && g->ops[wx].code == PC_SOP_MUL)) {
        const int mul_y = wy >= 0 && g->ops[wy].code == PC_SOP_MUL;
        init = mul_y ? x : y;
        pc_add_sum_term(g, mul_y ? y : x);
    } else {
        return pc_emit(g, PC_SOP_ADD, x, y, x, out, e);
    }
    return pc_emit_dot(g, init, t0, out, e);
}

/* Element e of act(A B + C) as pc_gemm_one and pc_gemm_rows compute it. */
static pc_status pc_expand_product(pc_prog *g, const pc_draft *d, size_t e)
{
    static const int act_code[] = {[PC_ACT_NONE] = 0, [PC_ACT_TANH] = PC_SOP_TANH,
                                   [PC_ACT_SIGMOID] = PC_SOP_SIGMOID,
                                   [PC_ACT_RELU] = PC_SOP_RELU};
    const pc_gemm *q = (const pc_gemm *)d->prm;
    const int rows = d->fn == pc_gemm_rows_kernels[0] || d->fn == pc_gemm_rows_kernels[1];
    const size_t MN = q->M * q->N, m = (e % MN) / q->N, n = e % q->N;
    const int c_mode = rows ? 2 : q->c_mode;
    const int32_t out = d->io[d->n_io - 1];
    size_t ao = 0, bo = 0, t = e / MN, k, j;
    const size_t t0 = g->n_terms;
    pc_eref init = pc_zero;
    pc_status st;
    for (j = q->nbd; d->fn == k_matmul && j-- > 0; t /= q->bd[j]) {
        ao += (t % q->bd[j]) * q->a_bst[j];
        bo += (t % q->bd[j]) * q->b_bst[j];
    }
    for (k = 0; k < q->K; k++) {
        pc_eref *tm = &g->terms[2 * g->n_terms++];
        tm[0] = pc_read(g, d->io[0], ao + (rows ? m * q->K + k : m * q->a_rs + k * q->a_cs));
        tm[1] = pc_read(g, d->io[1], bo + (rows ? k * q->N + n : k * q->b_rs + n * q->b_cs));
    }
    if (c_mode)
        init = pc_read(g, d->io[2], c_mode == 1 ? 0 : c_mode == 2 ? n : c_mode == 3 ? m : m * q->N + n);
    if ((st = pc_emit_dot(g, init, t0, out, e)) != PC_OK || !act_code[q->act])
        return st;
    {
        const pc_eref r = {pc_root(g->b, out), (uint32_t)e};
        return pc_emit(g, act_code[q->act], r, r, r, out, e);
    }
}

/* The element operations of one step, appended to g->ops. */
static pc_status pc_expand(pc_prog *g, const pc_draft *d)
{
    pc_builder *b = g->b;
    const int32_t out = d->io[d->n_io - 1];
    size_t e, k, i;
    pc_status st = PC_OK;
    if (d->sop) {
        const pc_value *ov = &b->values[out];
        const uint32_t n_in = d->n_io - 1;
        for (e = 0; e < d->n && st == PC_OK; e++) {
            pc_eref r[3];
            for (k = 0; k < n_in; k++)
                r[k] = pc_read(g, d->io[k], pc_bcast_element(&b->values[d->io[k]], ov, e));
            if (d->sop == PC_SOP_WHERE) /* io: condition, then, else */
                st = pc_emit(g, d->sop, r[1], r[2], r[0], out, e);
            else if (d->sop == PC_SOP_ADD)
                st = pc_expand_add(g, r[0], r[1], out, e);
            else
                st = pc_emit(g, d->sop, r[0], n_in > 1 ? r[1] : r[0], r[0], out, e);
        }
    } else if (d->fn == k_copy_4) {
        const pc_strided *q = (const pc_strided *)d->prm;
        for (e = 0; e < d->n && st == PC_OK; e++)
            st = pc_emit_copy(g, d->io[0], (size_t)q->base + e, out, e);
    } else if (d->fn == k_strided2_4) {
        const pc_strided *q = (const pc_strided *)d->prm;
        for (e = 0, i = 0; i < q->d[4]; i++)
            for (k = 0; k < q->d[5] && st == PC_OK; k++, e++)
                st = pc_emit_copy(g, d->io[0],
                                  (size_t)(q->base + (ptrdiff_t)i * q->st[4] +
                                           (ptrdiff_t)k * q->st[5]), out, e);
    } else if (d->fn == k_gather_cols_4) {
        const pc_gather *q = (const pc_gather *)d->prm;
        const int64_t *idx = (const int64_t *)b->values[pc_root(b, d->io[1])].cdata;
        for (e = 0, i = 0; i < q->outer; i++)
            for (k = 0; k < q->n_idx && st == PC_OK; k++, e++)
                st = pc_emit_copy(g, d->io[0], i * q->len + (size_t)idx[k], out, e);
    } else if (d->fn == k_concat) {
        const pc_concat *q = (const pc_concat *)d->prm;
        for (e = 0, i = 0; i < q->outer; i++)
            for (k = 0; k < q->n_in; k++) {
                size_t j;
                for (j = 0; j < q->inner[k] && st == PC_OK; j++, e++)
                    st = pc_emit_copy(g, d->io[k], i * q->inner[k] + j, out, e);
            }
    } else if (d->fn == k_reduce_sum_last) {
        /* the kernel sums from 0 in memory order: 0 + x0 + x1 ... (x 1 is exact) */
        const size_t len = ((const pc_reduce *)d->prm)->d[5];
        for (e = 0; e < d->n && st == PC_OK; e++) {
            const size_t t0 = g->n_terms;
            for (k = 0; k < len; k++)
                pc_add_sum_term(g, pc_read(g, d->io[0], e * len + k));
            st = pc_emit_dot(g, pc_zero, t0, out, e);
        }
    } else {
        for (e = 0; e < d->n && st == PC_OK; e++)
            st = pc_expand_product(g, d, e);
    }
    return st;
}

/* Pointers to the operands op reads, in in[0, returned count). */
static size_t pc_inputs(const pc_prog *g, const pc_eop *op, const pc_eref **in)
{
    size_t k, n = 0;
    if (op->code == PC_SOP_DOT) {
        in[n++] = &op->c;
        for (k = 0; k < 2 * op->nt; k++)
            in[n++] = &g->terms[2 * op->t0 + k];
        return n;
    }
    in[n++] = &op->a;
    if (op->code == PC_SOP_WHERE || PC_SOP_IS_BINARY(op->code))
        in[n++] = &op->b;
    if (op->code == PC_SOP_WHERE)
        in[n++] = &op->c;
    return n;
}

static int pc_is_live(const pc_prog *g, pc_eref r)
{
    return g->outside[r.v] || g->elem[r.v][r.e].live;
}

static void pc_mark(pc_prog *g, pc_eref r)
{
    if (r.v >= 0 && g->elem[r.v])
        g->elem[r.v][r.e].live = 1;
}

/* The order the kept operations run in: dependencies first, and as long as one is
 * ready, another of the same code, so that the interpreter dispatches once per group
 * instead of once per operation. Only independent operations trade places, each still
 * computes what it did, so results are unchanged. An operation depends on the last
 * earlier writer of each element it reads; an element written twice (a product, then
 * its activation in place) is read only after its last write. */
static pc_status pc_schedule(pc_prog *g, const pc_eref **in, int32_t *order,
                             size_t *n_order)
{
    pc_builder *b = g->b;
    const size_t n = g->n_ops, max_edges = 3 * n + 2 * g->n_terms;
    int32_t *pending, *succ_start, *succ, *fill, *ready, *edges, *height;
    size_t k, m, n_in, n_ready = 0, n_done = 0, n_kept = 0, n_edges = 0;
    int code = PC_SOP_NONE;
    pending = pc_scratch_alloc(&b->scratch, (n + 1) * sizeof(int32_t));
    succ_start = pc_scratch_alloc(&b->scratch, (n + 2) * sizeof(int32_t));
    fill = pc_scratch_alloc(&b->scratch, (n + 1) * sizeof(int32_t));
    ready = pc_scratch_alloc(&b->scratch, (n + 1) * sizeof(int32_t));
    height = pc_scratch_alloc(&b->scratch, (n + 1) * sizeof(int32_t));
    edges = pc_scratch_alloc_raw(&b->scratch, (2 * max_edges + 1) * sizeof(int32_t));
    succ = pc_scratch_alloc_raw(&b->scratch, (max_edges + 1) * sizeof(int32_t));
    if (!pending || !succ_start || !fill || !ready || !height || !edges || !succ)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    /* Edges from the last earlier writer of each operand, in the original order; then
     * the successors of w in succ[succ_start[w], succ_start[w + 1]). */
    for (k = 0; k < g->n_touched; k++)
        for (m = 0; m < b->values[g->touched[k]].count; m++)
            g->elem[g->touched[k]][m].writer = -1;
    for (k = 0; k < n; k++) {
        const pc_eop *op = &g->ops[k];
        if (op->code == PC_SOP_NONE)
            continue;
        for (m = 0, n_in = pc_inputs(g, op, in); m < n_in; m++) {
            const int32_t w = pc_writer(g, *in[m]);
            if (w >= 0) {
                edges[2 * n_edges] = w;
                edges[2 * n_edges++ + 1] = (int32_t)k;
                succ_start[w + 1]++;
                pending[k]++;
            }
        }
        g->elem[op->o.v][op->o.e].writer = (int32_t)k;
        n_kept++;
    }
    for (k = 0; k < n; k++)
        succ_start[k + 1] += succ_start[k];
    for (k = 0; k < n_edges; k++)
        succ[succ_start[edges[2 * k]] + fill[edges[2 * k]]++] = edges[2 * k + 1];
    for (k = 0; k < n; k++)
        if (g->ops[k].code != PC_SOP_NONE && pending[k] == 0)
            ready[n_ready++] = (int32_t)k;
    /* height: operations on the longest chain to the end, so the switch goes where the
     * run would otherwise wait (edges go forward in the original order) */
    for (k = n; k-- > 0;) {
        size_t j;
        height[k] = 1;
        for (j = (size_t)succ_start[k]; j < (size_t)succ_start[k + 1]; j++)
            if (height[succ[j]] + 1 > height[k])
                height[k] = height[succ[j]] + 1;
    }
    /* ready[] stays in original order; take the first of the current code, else the
     * highest. */
    while (n_ready) {
        size_t pick = n_ready, j;
        int32_t op_k;
        for (j = 0; j < n_ready; j++)
            if (g->ops[ready[j]].code == code) {
                pick = j;
                break;
            }
        if (pick == n_ready)
            for (pick = 0, j = 1; j < n_ready; j++)
                if (height[ready[j]] > height[ready[pick]])
                    pick = j;
        op_k = ready[pick];
        code = g->ops[op_k].code;
        memmove(ready + pick, ready + pick + 1, (n_ready - pick - 1) * sizeof(int32_t));
        n_ready--;
        order[n_done++] = op_k;
        for (j = (size_t)succ_start[op_k]; j < (size_t)succ_start[op_k + 1]; j++) {
            const int32_t next = succ[j];
            if (--pending[next] == 0) {
                size_t at = n_ready++;
                for (; at > 0 && ready[at - 1] > next; at--)
                    ready[at] = ready[at - 1];
                ready[at] = next;
            }
        }
    }
    if (n_done != n_kept)
        return pc_fail(b->err, PC_ERR_GRAPH, "one-pose program has a cycle");
    *n_order = n_done;
    return PC_OK;
}

/* The io slot of root v in this run's program, appended when new. */
static uint32_t pc_slot(const pc_prog *g, int32_t *io, uint32_t *n, int32_t v)
{
    if (g->slot_of[v] < 0) {
        g->slot_of[v] = (int32_t)*n;
        io[(*n)++] = v;
    }
    return (uint32_t)g->slot_of[v];
}

/* The planning form of operand r (PC_SOP_REF). */
static int32_t pc_ref(const pc_prog *g, int32_t *io, uint32_t *n_io, pc_eref r)
{
    const pc_builder *b = g->b;
    if (r.v >= 0 && g->elem[r.v] && g->elem[r.v][r.e].into.v >= 0)
        r = g->elem[r.v][r.e].into;
    if (r.v < 0)
        return PC_SOP_REF((uint32_t)PC_SOP_CONSTANTS, r.e * sizeof(float));
    return PC_SOP_REF(pc_slot(g, io, n_io, r.v), r.e * pc_dtype_size(b->values[r.v].dtype));
}

/* Compiles drafts[first, end) in scratch it takes and leaves for the caller to release;
 * the program's sizes go to *n_scalar and *n_io, and when q_out is given, the program and
 * its io list (value ids) are copied into q_out and io_out. */
static pc_status pc_compile_pass(pc_prog *g, const pc_plan_draft *pd, size_t first,
                                 size_t end, pc_scalar_program *q_out, int32_t *io_out,
                                 size_t *n_scalar_out, uint32_t *n_io_out)
{
    pc_builder *b = g->b;
    size_t i, k, m, n_in, cap_ops = 0, cap_terms = 0, n_kept = 0, n_scalar = 0;
    uint32_t j, n_io = 0;
    pc_scalar_program *q;
    int32_t *io, *order;
    const pc_eref **in;
    pc_status st;
    for (i = first; i < end; i++)
        pc_expansion_size(&pd->drafts[i], &cap_ops, &cap_terms);
    g->ops = pc_scratch_alloc_raw(&b->scratch, (cap_ops + 1) * sizeof(pc_eop));
    g->terms = pc_scratch_alloc_raw(&b->scratch, (2 * cap_terms + 1) * sizeof(pc_eref));
    in = pc_scratch_alloc_raw(&b->scratch, (2 * PC_PROGRAM_MAX_TERMS + 3) * sizeof *in);
    if (!g->ops || !g->terms || !in)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    g->n_ops = g->n_terms = 0;
    for (i = first; i < end; i++)
        if ((st = pc_expand(g, &pd->drafts[i])) != PC_OK)
            return st;
    /* Results read after the run (or returned) are kept whole. */
    for (i = end; i < pd->n_drafts; i++)
        for (j = 0; j < pd->drafts[i].n_io; j++)
            if (pd->drafts[i].io[j] >= 0)
                g->outside[pc_root(b, pd->drafts[i].io[j])] = 1;
    for (i = 0; i < b->n_outputs; i++)
        g->outside[pc_root(b, b->outputs[i].id)] = 1;
    /* Backwards: keep what a kept operation or the outside reads. */
    for (k = g->n_ops; k-- > 0;) {
        pc_eop *op = &g->ops[k];
        if (!pc_is_live(g, op->o)) {
            op->code = PC_SOP_NONE;
            continue;
        }
        n_kept++;
        n_scalar += op->code == PC_SOP_DOT ? op->nt : 1;
        for (m = 0, n_in = pc_inputs(g, op, in); m < n_in; m++)
            pc_mark(g, *in[m]);
    }
    /* A copy out of an element this run computes, read nowhere else after the run and
     * copied once, becomes the computation writing into the copy's place (the 'corrected'
     * concatenation of every model, the PMC features of a pipeline). */
    for (k = 0; k < g->n_ops; k++) {
        const pc_eop *op = &g->ops[k];
        pc_eref *into;
        if (op->code != PC_SOP_COPY || pc_writer(g, op->a) < 0 || g->outside[op->a.v])
            continue;
        into = &g->elem[op->a.v][op->a.e].into;
        if (into->v == -1)
            *into = op->o;
        else
            into->v = PC_COPIED_TWICE;
    }
    for (k = 0; k < g->n_ops; k++) {
        pc_eop *op = &g->ops[k];
        if (op->code == PC_SOP_COPY && pc_writer(g, op->a) >= 0 &&
            g->elem[op->a.v][op->a.e].into.v == op->o.v &&
            g->elem[op->a.v][op->a.e].into.e == op->o.e) {
            op->code = PC_SOP_NONE;
            n_kept--;
            n_scalar--;
        }
    }
    order = pc_scratch_alloc(&b->scratch, (n_kept + 1) * sizeof(int32_t));
    io = pc_scratch_alloc(&b->scratch, (4 * n_scalar + 2) * sizeof(int32_t));
    q = pc_scratch_alloc(&b->scratch, sizeof *q + n_scalar * sizeof(pc_scalar_op));
    if (!order || !io || !q)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    if ((st = pc_schedule(g, in, order, &n_kept)) != PC_OK)
        return st;
    {
        pc_scalar_op *group = NULL;
        for (k = 0; k < n_kept; k++) {
            const pc_eop *op = &g->ops[order[k]];
            const int32_t o = pc_ref(g, io, &n_io, op->o);
            if (op->code == PC_SOP_DOT) {
                /* a DOT entry with the start c, then one DOT_TERM per further term */
                const pc_eref *t = &g->terms[2 * op->t0];
                if (!group || group->code != PC_SOP_DOT)
                    group = &q->ops[q->n_ops];
                group->n += (int32_t)op->nt;
                for (m = 0; m < op->nt; m++) {
                    pc_scalar_op *so = &q->ops[q->n_ops++];
                    so->code = m ? PC_SOP_DOT_TERM : PC_SOP_DOT;
                    so->a = pc_ref(g, io, &n_io, t[2 * m]);
                    so->b = pc_ref(g, io, &n_io, t[2 * m + 1]);
                    so->c = pc_ref(g, io, &n_io, op->c);
                    so->o = o;
                }
                continue;
            }
            {
                pc_scalar_op *so = &q->ops[q->n_ops++];
                /* group length on the first op of each run of one code */
                if (!group || group->code != op->code)
                    group = so;
                group->n++;
                so->code = op->code;
                so->o = o;
                so->a = pc_ref(g, io, &n_io, op->a);
                so->b = pc_ref(g, io, &n_io, op->b);
                so->c = pc_ref(g, io, &n_io, op->c);
            }
        }
    }
    if (n_io == 0) /* nothing but constants: io[0] still anchors the offsets */
        io[n_io++] = pc_root(b, pd->drafts[first].io[0]);
    /* reset the per-root state this run used */
    for (i = 0; i < g->n_touched; i++) {
        g->elem[g->touched[i]] = NULL;
    }
    g->n_touched = 0;
    memset(g->outside, 0, b->n_values);
    for (j = 0; j < n_io; j++)
        g->slot_of[io[j]] = -1;
    *n_scalar_out = q->n_ops;
    *n_io_out = n_io;
    if (q_out) {
        memcpy(q_out, q, sizeof *q + (q->n_ops ? q->n_ops - 1 : 0) * sizeof(pc_scalar_op));
        memcpy(io_out, io, n_io * sizeof(int32_t));
    }
    return PC_OK;
}

/* drafts[first, end) -> one program draft in *out. Compiled twice: once for its sizes,
 * once into memory of those sizes, each time releasing the working memory, so the load's
 * scratch peak (what pc_required_bytes asks of a target without a heap) stays low. */
static pc_status pc_compile_run(pc_prog *g, const pc_plan_draft *pd, size_t first,
                                size_t end, pc_draft *out)
{
    pc_scratch *scratch = &g->b->scratch;
    pc_scratch_mark mark = pc_scratch_save(scratch);
    pc_scalar_program *q;
    int32_t *io;
    size_t n_scalar;
    uint32_t n_io;
    pc_status st;
    if ((st = pc_compile_pass(g, pd, first, end, NULL, NULL, &n_scalar, &n_io)) != PC_OK)
        return st;
    pc_scratch_restore(scratch, mark);
    q = pc_scratch_alloc(scratch, sizeof *q + n_scalar * sizeof(pc_scalar_op));
    io = pc_scratch_alloc(scratch, (n_io + 1) * sizeof(int32_t));
    if (!q || !io)
        return pc_fail(g->b->err, PC_ERR_MEMORY, "out of memory");
    mark = pc_scratch_save(scratch);
    if ((st = pc_compile_pass(g, pd, first, end, q, io, &n_scalar, &n_io)) != PC_OK)
        return st;
    pc_scratch_restore(scratch, mark);
    out->fn = k_scalar_program;
    out->io = io;
    out->n_io = n_io;
    out->prm = q;
    out->prm_size = sizeof *q + (n_scalar ? n_scalar - 1 : 0) * sizeof(pc_scalar_op);
    out->n = 1;
    out->sop = 0;
    return PC_OK;
}

pc_status pc_fuse_small_steps(pc_builder *b, pc_plan_draft *pd)
{
    size_t i = 0, w = 0, j, io_total;
    pc_prog g;
    pc_status st;
    memset(&g, 0, sizeof g);
    g.b = b;
    g.elem = pc_scratch_alloc(&b->scratch, (b->n_values + 1) * sizeof *g.elem);
    g.outside = pc_scratch_alloc(&b->scratch, b->n_values + 1);
    g.slot_of = pc_scratch_alloc_raw(&b->scratch, (b->n_values + 1) * sizeof *g.slot_of);
    g.touched = pc_scratch_alloc(&b->scratch, (b->n_values + 1) * sizeof *g.touched);
    if (!g.elem || !g.outside || !g.slot_of || !g.touched)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    memset(g.slot_of, 0xff, (b->n_values + 1) * sizeof *g.slot_of);
    while (i < pd->n_drafts) {
        for (j = i, io_total = 0; j < pd->n_drafts && pc_expandable(b, &pd->drafts[j]) &&
                                  io_total + pd->drafts[j].n_io <= PC_PROGRAM_MAX_SLOTS;
             j++)
            io_total += pd->drafts[j].n_io;
        if (j - i >= 2) {
            pc_draft fused;
            if ((st = pc_compile_run(&g, pd, i, j, &fused)) != PC_OK)
                return st;
            pd->drafts[w++] = fused;
            i = j;
        } else {
            pd->drafts[w++] = pd->drafts[i++];
        }
    }
    pd->n_drafts = w;
    return PC_OK;
}
