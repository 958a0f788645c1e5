/* Dense operators: Gemm and MatMul (kernels in dense.c). */
#include "op.h"

#include <float.h>
#include <math.h>
#include <string.h>

/* ---- Gemm, MatMul ----------------------------------------------------------------- */

/* A product whose elements a one-pose program computes exactly as the kernels do
 * (pc_gemm_one, pc_gemm_rows: C first, then the products for k ascending): alpha 1, C
 * absent or taken with beta 1, an activation the programs know. */
static void pc_product(pc_prep *p, const pc_gemm *q)
{
    if (q->alpha == 1.0f && (q->c_mode == 0 || q->beta == 1.0f) &&
        (q->act == PC_ACT_NONE || q->act == PC_ACT_TANH || q->act == PC_ACT_SIGMOID ||
         q->act == PC_ACT_RELU || q->act == PC_ACT_RADBAS))
        p->emap = PC_EMAP_PRODUCT;
}


/* How Gemm's C broadcasts to [M, N] (q->c_mode); without C, an empty third input. */
static pc_status pc_gemm_bias(pc_prep *p, pc_gemm *q, const pc_value *c)
{
    size_t cn, cm;
    q->c_mode = 0;
    if (!c)
        return pc_pad_inputs(p, 3);
    cn = c->rank >= 1 ? (size_t)c->dims[c->rank - 1] : 1;
    cm = c->rank >= 2 ? (size_t)c->dims[c->rank - 2] : 1;
    if (c->rank > 2 || (cn != 1 && cn != q->N) || (cm != 1 && cm != q->M))
        return pc_prep_fail(p, PC_ERR_SHAPE, "C cannot be broadcast to [M,N]");
    q->c_mode = c->count == 1 ? 1 : cm == 1 ? 2 : cn == 1 ? 3 : 4;
    if (q->c_mode == 2 && q->N == 1)
        q->c_mode = 1;
    return PC_OK;
}

pc_status pc_op_Gemm(pc_prep *p)
{
    int64_t ta, tb, dims[2];
    pc_gemm *q;
    const pc_value *a, *b, *c;
    pc_status s;
    if (p->n_in < 2 || !p->in[0] || !p->in[1] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs A and B");
    a = p->in[0];
    b = p->in[1];
    c = p->n_in > 2 ? p->in[2] : NULL;
    if (a->dtype != PC_F32 || b->dtype != PC_F32 || (c && c->dtype != PC_F32))
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "only float32 is supported");
    if (a->rank != 2 || b->rank != 2)
        return pc_prep_fail(p, PC_ERR_SHAPE, "A and B must be 2-D");
    q = pc_prep_params(p, sizeof *q);
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    if ((s = pc_attr_int(p, "transA", 0, &ta)) != PC_OK ||
        (s = pc_attr_int(p, "transB", 0, &tb)) != PC_OK ||
        (s = pc_attr_float(p, "alpha", 1.0f, &q->alpha)) != PC_OK ||
        (s = pc_attr_float(p, "beta", 1.0f, &q->beta)) != PC_OK)
        return s;
    q->M = (size_t)(ta ? a->dims[1] : a->dims[0]);
    q->K = (size_t)(ta ? a->dims[0] : a->dims[1]);
    q->N = (size_t)(tb ? b->dims[0] : b->dims[1]);
    if ((size_t)(tb ? b->dims[1] : b->dims[0]) != q->K)
        return pc_prep_fail(p, PC_ERR_SHAPE, "inner dimensions differ (%zu vs %lld)", q->K,
                            (long long)(tb ? b->dims[1] : b->dims[0]));
    q->a_rs = ta ? 1 : q->K;
    q->a_cs = ta ? q->M : 1;
    /* A transposed B is read where it lies (strided), never copied: posecorr's exporter
     * writes B as [K, N], and a model in flash keeps its weights there. */
    q->b_rs = tb ? 1 : q->N;
    q->b_cs = tb ? q->K : 1;
    if ((s = pc_gemm_bias(p, q, c)) != PC_OK)
        return s;
    q->act = p->node->act;
    q->lo = p->node->act_lo;
    q->hi = p->node->act_hi;
    dims[0] = (int64_t)q->M;
    dims[1] = (int64_t)q->N;
    p->fn = k_gemm;
    pc_product(p, q);
    /* the MLP layer: a bias row (one output's bias is also its scalar), any activation */
    if (!ta && !tb && (q->c_mode == 2 || (q->c_mode == 1 && q->N == 1)) && q->alpha == 1.0f &&
        q->beta == 1.0f) {
        if (p->b->cpu_avx2 < 0)
            p->b->cpu_avx2 = pc_cpu_avx2(); /* cpuid traps to the hypervisor in a VM: ask once */
        p->fn = pc_gemm_rows_kernels[p->b->cpu_avx2];
        p->layer = 1;
    }
    return pc_set_out(p, 0, PC_F32, 2, dims);
}

/* An operand's dims, a 1-D one promoted as numpy does ([K] -> [1, K] for A, [K, 1] for B);
 * returns its rank and sets *dropped: the added axis is left out of the output. */
static int pc_matmul_dims(const pc_value *v, int is_b, int64_t *d, int *dropped)
{
    int j;
    for (j = 0; j < v->rank; j++)
        d[j] = v->dims[j];
    *dropped = v->rank == 1;
    if (v->rank != 1)
        return v->rank;
    if (is_b) {
        d[1] = 1;
    } else {
        d[1] = d[0];
        d[0] = 1;
    }
    return 2;
}

/* The batch dimensions (all but the last two, broadcast against each other): their sizes
 * into q and od[*r...], each operand's stride per batch (0 where it broadcasts). B shared by
 * all batches and A contiguous fold into one [M*batch, K] product. */
static pc_status pc_matmul_batch(pc_prep *p, pc_gemm *q, const int64_t *ad, int ar,
                                 const int64_t *bd, int br, int64_t *od, int *r)
{
    const int nb = (ar > br ? ar : br) - 2;
    size_t ast = q->M * q->K, bst = q->K * q->N, tot = 1;
    int j, b_shared = 1;
    if (nb > 4)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "more than 4 batch dimensions");
    for (j = nb - 1; j >= 0; j--) {
        const int ja = ar - 2 - nb + j, jb = br - 2 - nb + j;
        const int64_t da = ja >= 0 ? ad[ja] : 1, db = jb >= 0 ? bd[jb] : 1;
        if (da != db && da != 1 && db != 1)
            return pc_prep_fail(p, PC_ERR_SHAPE, "batch dimensions cannot be broadcast");
        q->bd[j] = (size_t)(da > db ? da : db);
        if (da == 0 || db == 0)
            q->bd[j] = 0;
        q->a_bst[j] = da == 1 ? 0 : ast;
        q->b_bst[j] = db == 1 ? 0 : bst;
        ast *= (size_t)da;
        bst *= (size_t)db;
    }
    for (j = 0; j < nb; j++) {
        od[(*r)++] = (int64_t)q->bd[j];
        b_shared &= q->b_bst[j] == 0;
        tot *= q->bd[j];
    }
    q->nbd = (size_t)nb;
    if (b_shared && nb > 0 && ar - 2 == nb) {
        q->M *= tot;
        q->nbd = 0;
    }
    return PC_OK;
}

pc_status pc_op_MatMul(pc_prep *p)
{
    const pc_value *a, *b;
    int64_t ad[PC_MAX_RANK], bd[PC_MAX_RANK], od[PC_MAX_RANK];
    int ar, br, r = 0, oa, ob;
    pc_gemm *q;
    pc_status s;
    if (p->n_in != 2 || !p->in[0] || !p->in[1] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 2 inputs");
    a = p->in[0];
    b = p->in[1];
    if (a->dtype != PC_F32 || b->dtype != PC_F32)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "only float32 is supported");
    if (a->rank < 1 || b->rank < 1)
        return pc_prep_fail(p, PC_ERR_SHAPE, "inputs must have rank >= 1");
    ar = pc_matmul_dims(a, 0, ad, &oa);
    br = pc_matmul_dims(b, 1, bd, &ob);
    if (ad[ar - 1] != bd[br - 2])
        return pc_prep_fail(p, PC_ERR_SHAPE, "inner dimensions differ (%lld vs %lld)",
                            (long long)ad[ar - 1], (long long)bd[br - 2]);
    q = pc_prep_params(p, sizeof *q);
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    q->M = (size_t)ad[ar - 2];
    q->K = (size_t)ad[ar - 1];
    q->N = (size_t)bd[br - 1];
    q->a_rs = q->K;
    q->a_cs = 1;
    q->b_rs = q->N;
    q->b_cs = 1;
    q->alpha = 1.0f;
    q->beta = 0.0f;
    if ((s = pc_matmul_batch(p, q, ad, ar, bd, br, od, &r)) != PC_OK)
        return s;
    if (!oa)
        od[r++] = ad[ar - 2];
    if (!ob)
        od[r++] = bd[br - 1];
    p->fn = k_matmul;
    pc_product(p, q);
    return pc_set_out(p, 0, PC_F32, r, od);
}
