/* The hand-written tanh MLP (see zhou_reference.h). Every line is one operation of the
 * exported graph, in its order, so rounding matches the runtime's step by step. */
#include "zhou_reference.h"

#include "kernels.h" /* pc_tanh_inline: the runtime's tanh */

#include <math.h>

static float norm_of(float n2)
{
    return sqrtf(n2 > 1e-24f ? n2 : 1e-24f);
}

/* One dense layer o = act(x W + b): each output sums bias, then x[k] W[k][n] in k order
 * (as the runtime does), with k outermost so the n loop vectorises. A layer has at least
 * one input and one output: the loops test at their end, one branch per multiply-add. */
static void dense(const float *x, const pc_mlp_layer *l, int tanh_act, float *restrict o)
{
    /* the sizes and weights in locals: o's stores cannot make the compiler reload them */
    const size_t k_in = l->k, n_out = l->n;
    const float *restrict w = l->w, *b = l->b;
    size_t n, k;
    for (n = 0; n < n_out; n++)
        o[n] = b[n];
    k = 0;
    do { /* W's rows in order: w walks W once */
        const float xk = x[k];
        float *on = o;
        do
            *on += xk * *w++;
        while (++on != o + n_out);
    } while (++k < k_in);
    if (tanh_act)
        for (n = 0; n < n_out; n++)
            o[n] = pc_tanh_inline(o[n]);
}

/* q[4] (w, x, y, z), normalised first -> the rotation matrix r[9], rows first. */
static void quat_matrix(const float *q4, float *r)
{
    const float n2 = 0.0f + q4[0] * q4[0] + q4[1] * q4[1] + q4[2] * q4[2] + q4[3] * q4[3];
    const float s = norm_of(n2);
    const float qw = q4[0] / s, qx = q4[1] / s, qy = q4[2] / s, qz = q4[3] / s;
    r[0] = 1.0f - (qy * qy + qz * qz) * 2.0f;
    r[1] = (qx * qy - qw * qz) * 2.0f;
    r[2] = (qx * qz + qw * qy) * 2.0f;
    r[3] = (qx * qy + qw * qz) * 2.0f;
    r[4] = 1.0f - (qx * qx + qz * qz) * 2.0f;
    r[5] = (qy * qz - qw * qx) * 2.0f;
    r[6] = (qx * qz - qw * qy) * 2.0f;
    r[7] = (qy * qz + qw * qx) * 2.0f;
    r[8] = 1.0f - (qx * qx + qy * qy) * 2.0f;
}

static void quarter(float t, float a, float b, float c, int slot, float *q)
{
    const float m = t > 1e-12f ? t : 1e-12f;
    const float k = 1.0f / (sqrtf(m) * 2.0f);
    float v[3];
    v[0] = a * k;
    v[1] = b * k;
    v[2] = c * k;
    /* t * k goes into position slot, the three others fill the rest in order */
    q[0] = slot == 0 ? t * k : v[0];
    q[1] = slot == 1 ? t * k : slot == 0 ? v[0] : v[1];
    q[2] = slot == 2 ? t * k : slot < 2 ? v[1] : v[2];
    q[3] = slot == 3 ? t * k : v[2];
}

/* The rotation matrix r[9] -> the unit quaternion q[4] with qw >= 0, from the largest of
 * the four diagonal combinations. */
static void matrix_quat(const float *r, float *q)
{
    const float r00 = r[0], r01 = r[1], r02 = r[2], r10 = r[3], r11 = r[4], r12 = r[5];
    const float r20 = r[6], r21 = r[7], r22 = r[8];
    float t0, t1, t2, t3, qa[4], qb[4], qc[4], qd[4], s, n2;
    const float *pick;
    int i;

    t0 = r00 + 1.0f + r11 + r22;
    t1 = r00 + 1.0f - r11 - r22;
    t2 = 1.0f - r00 + r11 - r22;
    t3 = 1.0f - r00 - r11 + r22;
    quarter(t0, r21 - r12, r02 - r20, r10 - r01, 0, qa);
    quarter(t1, r21 - r12, r01 + r10, r02 + r20, 1, qb);
    quarter(t2, r02 - r20, r01 + r10, r12 + r21, 2, qc);
    quarter(t3, r10 - r01, r02 + r20, r12 + r21, 3, qd);
    pick = (t0 > t1 ? t0 : t1) >= (t2 > t3 ? t2 : t3) ? (t0 >= t1 ? qa : qb)
                                                      : (t2 >= t3 ? qc : qd);
    n2 = 0.0f + pick[0] * pick[0] + pick[1] * pick[1] + pick[2] * pick[2] + pick[3] * pick[3];
    s = norm_of(n2);
    for (i = 0; i < 4; i++)
        q[i] = pick[i] / s;
    if (q[0] < 0.0f)
        for (i = 0; i < 4; i++)
            q[i] = -q[i];
}

/* Gram-Schmidt on the two columns y[0..5], their cross product the third -> r[9]. */
static void zhou_matrix(const float *y, float *r)
{
    float s, e1[3], e2[3], u[3], d, n2;
    int i;

    n2 = 0.0f + y[0] * y[0] + y[1] * y[1] + y[2] * y[2];
    s = norm_of(n2);
    for (i = 0; i < 3; i++)
        e1[i] = y[i] / s;
    d = 0.0f + e1[0] * y[3] + e1[1] * y[4] + e1[2] * y[5];
    for (i = 0; i < 3; i++)
        u[i] = y[3 + i] - d * e1[i];
    n2 = 0.0f + u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
    s = norm_of(n2);
    for (i = 0; i < 3; i++)
        e2[i] = u[i] / s;
    for (i = 0; i < 3; i++) {
        r[3 * i] = e1[i];
        r[3 * i + 1] = e2[i];
    }
    r[2] = e1[1] * e2[2] - e1[2] * e2[1];
    r[5] = e1[2] * e2[0] - e1[0] * e2[2];
    r[8] = e1[0] * e2[1] - e1[1] * e2[0];
}

size_t pc_mlp_width(const pc_mlp *m)
{
    return m->encoding == PC_MLP_ZHOU ? PC_ZHOU_IN : PC_QUAT_IN;
}

void pc_mlp_encode(const pc_mlp *m, const float *in, float *x)
{
    float r[9];
    size_t i;

    x[0] = in[0];
    x[1] = in[1];
    x[2] = in[2];
    quat_matrix(in + 3, r);
    if (m->encoding == PC_MLP_ZHOU)
        for (i = 0; i < 3; i++) {
            x[3 + i] = r[3 * i];     /* first column */
            x[6 + i] = r[3 * i + 1]; /* second column */
        }
    else
        matrix_quat(r, x + 3);
    for (i = 0; i < pc_mlp_width(m); i++)
        x[i] = x[i] * m->in_scale[i] + m->in_offset[i];
}

void pc_mlp_network(const pc_mlp *m, const float *x, float *y)
{
    float h[PC_MLP_MAX_WIDTH], g[PC_MLP_MAX_WIDTH];
    size_t i, l;

    if (m->layers == 1) {
        dense(x, &m->layer[0], 0, y);
        return;
    }
    dense(x, &m->layer[0], 1, h);
    for (l = 1; l + 1 < m->layers; l++) {
        dense(h, &m->layer[l], 1, g);
        for (i = 0; i < m->layer[l].n; i++)
            h[i] = g[i];
    }
    dense(h, &m->layer[m->layers - 1], 0, y);
}

void pc_mlp_decode(const pc_mlp *m, const float *y_net, float *out)
{
    float y[PC_ZHOU_IN], r[9];
    size_t i;

    for (i = 0; i < pc_mlp_width(m); i++)
        y[i] = y_net[i] * m->out_scale[i] + m->out_offset[i];
    if (m->encoding == PC_MLP_ZHOU)
        zhou_matrix(y + 3, r);
    else
        quat_matrix(y + 3, r);
    out[0] = y[0];
    out[1] = y[1];
    out[2] = y[2];
    matrix_quat(r, out + 3);
}

void pc_mlp_reference(const pc_mlp *m, const float *in, float *out)
{
    float x[PC_ZHOU_IN], y[PC_ZHOU_IN];
    pc_mlp_encode(m, in, x);
    pc_mlp_network(m, x, y);
    pc_mlp_decode(m, y, out);
}

void pc_zhou_describe(const pc_zhou_weights *w, pc_mlp_layer layer[PC_ZHOU_LAYERS], pc_mlp *m)
{
    size_t l;
    layer[0] = (pc_mlp_layer){PC_ZHOU_IN, PC_ZHOU_HIDDEN, w->w_in, w->b_in};
    for (l = 0; l < PC_ZHOU_LAYERS - 2; l++)
        layer[l + 1] = (pc_mlp_layer){PC_ZHOU_HIDDEN, PC_ZHOU_HIDDEN, w->w_hidden[l], w->b_hidden[l]};
    layer[PC_ZHOU_LAYERS - 1] = (pc_mlp_layer){PC_ZHOU_HIDDEN, PC_ZHOU_IN, w->w_out, w->b_out};
    *m = (pc_mlp){PC_MLP_ZHOU, PC_ZHOU_LAYERS, layer, w->in_scale, w->in_offset, w->out_scale,
                  w->out_offset};
}
