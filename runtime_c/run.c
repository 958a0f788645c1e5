/* pc_run: validate, then walk the precomputed plans. n is split greedily into chunks of
 * the planned batch sizes (max_batch, ..., 256, 16, 1) so every chunk runs a plan whose
 * shapes, pointers and kernels were fixed at load. */
#include "pc_internal.h"

#include <math.h>
#include <string.h>

static pc_status pc_run_plan(pc_model *m, const pc_plan *plan, const float *in, float *out)
{
    const pc_step *s = plan->steps;
    const pc_step *const end = s + plan->n_steps;
    const size_t count = plan->batch * PC_POSE_WIDTH;
    memcpy(plan->in, in, count * sizeof(float));
    for (; s < end; s++) {
        const pc_status st = s->fn(s);
        if (st != PC_OK) {
            snprintf(m->message, sizeof m->message, "step %zu of the N=%zu plan failed: %s",
                     (size_t)(s - plan->steps), plan->batch, pc_status_name(st));
            return st;
        }
    }
    memmove(out, plan->out, count * sizeof(float));
    return PC_OK;
}

pc_status pc_run(pc_model *model, const float *in, size_t n, float *out)
{
    size_t i, k, done = 0;
    if (!model)
        return PC_ERR_ARGUMENT;
    if (n == 0)
        return PC_OK;
    if (!in || !out) {
        snprintf(model->message, sizeof model->message, "pc_run: NULL %s buffer",
                 in ? "output" : "input");
        return PC_ERR_ARGUMENT;
    }
    if (n > ((size_t)-1) / (PC_POSE_WIDTH * sizeof(float))) {
        snprintf(model->message, sizeof model->message, "pc_run: n = %zu is too large", n);
        return PC_ERR_ARGUMENT;
    }
    /* Reject before writing anything, so that out is untouched on error. */
    for (i = 0; i < n * PC_POSE_WIDTH; i++) {
        if (!isfinite(in[i])) {
            snprintf(model->message, sizeof model->message,
                     "pose %zu has a non-finite value in column %zu", i / PC_POSE_WIDTH,
                     i % PC_POSE_WIDTH);
            return PC_ERR_NONFINITE;
        }
    }
    model->message[0] = '\0';
    if (n == 1)
        return pc_run_plan(model, &model->plans[0], in, out);
    while (done < n) {
        const size_t left = n - done;
        pc_status st;
        for (k = model->n_plans - 1; model->plans[k].batch > left; k--)
            ;
        st = pc_run_plan(model, &model->plans[k], in + done * PC_POSE_WIDTH,
                         out + done * PC_POSE_WIDTH);
        if (st != PC_OK)
            return st;
        done += model->plans[k].batch;
    }
    return PC_OK;
}
