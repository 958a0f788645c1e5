/* pc_run: validate, then walk the precomputed plans. n is split greedily into chunks of
 * the planned batch sizes (max_batch, ..., 256, 16, 1) so every chunk runs a plan whose
 * shapes, pointers and kernels were fixed at load; each chunk's result is checked
 * before it is copied out. */
#include "model.h"

#include <math.h>
#include <string.h>

/* |q|^2 of a float32 unit quaternion after a few dozen operations is within 1e-5 of 1;
 * anything beyond 1e-3 is not a rotation. */
#define PC_UNIT_TOLERANCE 1e-3f

pc_status pc_run_steps(pc_model *m, const pc_plan *plan)
{
    const pc_step *s = plan->steps;
    const pc_step *const end = s + plan->n_steps;
    for (; s < end; s++) {
        const pc_status st = s->fn(s);
        if (st != PC_OK) {
            pc_format(m->message, sizeof m->message, "step %zu of the N=%zu plan failed: %s",
                      (size_t)(s - plan->steps), plan->batch, pc_status_name(st));
            return st;
        }
    }
    return PC_OK;
}

/* The output contract: finite, and (posecorr's models) a unit quaternion. */
static pc_status pc_check_output(pc_model *m, const float *out, size_t n, size_t first)
{
    size_t r, c;
    for (r = 0; r < n; r++) {
        const float *p = out + r * PC_POSE_WIDTH;
        float n2 = 0.0f;
        for (c = 0; c < PC_POSE_WIDTH; c++) {
            if (!isfinite(p[c])) {
                pc_format(m->message, sizeof m->message,
                          "output 'corrected' of pose %zu is not finite in column %zu",
                          first + r, c);
                return PC_ERR_RUNTIME;
            }
            if (c >= 3)
                n2 += p[c] * p[c];
        }
        if (m->check_quaternion && !(fabsf(n2 - 1.0f) <= PC_UNIT_TOLERANCE)) {
            pc_format(m->message, sizeof m->message,
                      "output 'corrected' of pose %zu has a quaternion that is not unit "
                      "(columns 3-6)", first + r);
            return PC_ERR_RUNTIME;
        }
    }
    return PC_OK;
}

/* t NULL: every pose at t = 0. */
static pc_status pc_run_plan(pc_model *m, const pc_plan *plan, const float *in, const float *t,
                             float *out, size_t first)
{
    const size_t count = plan->batch * PC_POSE_WIDTH;
    size_t i;
    pc_status st;
    if (plan->batch == 1) /* one pose: seven values, not a library call */
        for (i = 0; i < PC_POSE_WIDTH; i++)
            plan->in[i] = in[i];
    else
        memcpy(plan->in, in, count * sizeof(float));
    if (plan->t) {
        if (t)
            memcpy(plan->t, t, plan->batch * sizeof(float));
        else
            memset(plan->t, 0, plan->batch * sizeof(float));
    }
    if ((st = pc_run_steps(m, plan)) != PC_OK ||
        (st = pc_check_output(m, plan->out, plan->batch, first)) != PC_OK)
        return st;
    if (plan->batch == 1)
        for (i = 0; i < PC_POSE_WIDTH; i++)
            out[i] = plan->out[i];
    else /* the caller's out never overlaps the arena */
        memcpy(out, plan->out, count * sizeof(float));
    return PC_OK;
}

/* Finite input inside the training box (when the model records one), finite times. */
static pc_status pc_check_input(pc_model *m, const float *in, const float *t, size_t n)
{
    size_t i, c;
    for (i = 0; t && i < n; i++)
        if (!isfinite(t[i])) {
            pc_format(m->message, sizeof m->message, "time of pose %zu is not finite", i);
            return PC_ERR_NONFINITE;
        }
    for (i = 0; i < n; i++, in += PC_POSE_WIDTH) {
        for (c = 0; c < PC_POSE_WIDTH; c++)
            if (!isfinite(in[c])) {
                pc_format(m->message, sizeof m->message,
                          "pose %zu has a non-finite value in column %zu", i, c);
                return PC_ERR_NONFINITE;
            }
        for (c = 0; m->has_bounds && c < 3; c++)
            if (!(in[c] >= m->lo[c] && in[c] <= m->hi[c])) {
                pc_format(m->message, sizeof m->message,
                          "pose %zu is outside the range the model was fitted on in column %zu "
                          "(metadata input_bounds)", i, c);
                return PC_ERR_RANGE;
            }
    }
    return PC_OK;
}

pc_status pc_run(pc_model *model, const float *in, size_t n, float *out)
{
    return pc_run_timed(model, in, NULL, n, out);
}

pc_status pc_run_timed(pc_model *model, const float *in, const float *t, size_t n, float *out)
{
    size_t k, done = 0;
    pc_status st;
    if (!model)
        return PC_ERR_ARGUMENT;
    if (n == 0)
        return PC_OK;
    if (!in || !out) {
        pc_format(model->message, sizeof model->message, "pc_run: NULL %s buffer",
                  in ? "output" : "input");
        return PC_ERR_ARGUMENT;
    }
    if (n > ((size_t)-1) / (PC_POSE_WIDTH * sizeof(float))) {
        pc_format(model->message, sizeof model->message, "pc_run: n = %zu is too large", n);
        return PC_ERR_ARGUMENT;
    }
    /* Reject before writing anything, so that out is untouched on these errors. */
    if ((st = pc_check_input(model, in, t, n)) != PC_OK)
        return st;
    model->message[0] = '\0';
    if (n == 1)
        return pc_run_plan(model, &model->plans[0], in, t, out, 0);
    while (done < n) {
        const size_t left = n - done;
        for (k = model->n_plans - 1; model->plans[k].batch > left; k--)
            ;
        st = pc_run_plan(model, &model->plans[k], in + done * PC_POSE_WIDTH,
                         t ? t + done : NULL, out + done * PC_POSE_WIDTH, done);
        if (st != PC_OK)
            return st;
        done += model->plans[k].batch;
    }
    return PC_OK;
}
