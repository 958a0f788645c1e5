/* Test-only entry points (libposecorr_testing.so, built with PC_BUILD_TESTS): load a
 * model with any input and output names of static shape, as ONNX's node tests have,
 * and run it on the caller's buffers. Not part of the public API. */
#include "load.h"

#include <string.h>

#if defined(__GNUC__)
#define PC_TEST_API __attribute__((visibility("default")))
#else
#define PC_TEST_API
#endif

PC_TEST_API pc_status pc_test_load(const void *data, size_t size, pc_model **model,
                                   pc_error *err)
{
    return pc_load_impl(data, size, NULL, 1, NULL, 0, model, NULL, err);
}

PC_TEST_API size_t pc_test_input_count(const pc_model *m)
{
    return m->n_in_slots;
}

PC_TEST_API size_t pc_test_output_count(const pc_model *m)
{
    return m->n_out_slots;
}

/* Bytes of input k (k < inputs) or output k - inputs. */
PC_TEST_API size_t pc_test_slot_bytes(const pc_model *m, size_t k)
{
    return k < m->n_in_slots + m->n_out_slots ? m->slots[k].bytes : 0;
}

/* in[k]: input k in graph order (float32, int64 or bool as uint8); out[k] likewise. */
PC_TEST_API pc_status pc_test_run(pc_model *m, const void *const *in, void *const *out)
{
    size_t k;
    pc_status st;
    for (k = 0; k < m->n_in_slots; k++)
        if (m->slots[k].bytes)
            memcpy(m->slots[k].data, in[k], m->slots[k].bytes);
    if ((st = pc_run_steps(m, &m->plans[0])) != PC_OK)
        return st;
    for (k = 0; k < m->n_out_slots; k++) {
        const pc_slot *s = &m->slots[m->n_in_slots + k];
        if (s->bytes)
            memcpy(out[k], s->data, s->bytes);
    }
    return PC_OK;
}

/* Steps of the one-pose plan that run a compiled program (*compiled) or the interpreter
 * (*interpreted): the tests check which the shipped models get. */
PC_TEST_API void pc_test_program_steps(const pc_model *m, size_t *compiled, size_t *interpreted)
{
    const pc_plan *plan = &m->plans[0];
    size_t i, k;
    *compiled = *interpreted = 0;
    for (i = 0; i < plan->n_steps; i++) {
        const pc_kernel_fn fn = plan->steps[i].fn;
        if (fn == k_scalar_program || fn == k_scalar_program16)
            ++*interpreted;
        for (k = 0; k < pc_n_compiled_programs; k++)
            if (fn == pc_compiled_programs[k].fn)
                ++*compiled;
    }
}

PC_TEST_API int pc_test_cpu_avx2(void)
{
    return pc_cpu_avx2();
}
