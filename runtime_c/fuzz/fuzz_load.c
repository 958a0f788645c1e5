/* libFuzzer target: the loader and, when a model loads, pc_run on a few poses. */
#include "posecorr.h"

#include <math.h>
#include <stddef.h>
#include <stdint.h>

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    pc_model *m = NULL;
    pc_error err;
    float in[5 * 7], out[5 * 7];
    size_t i;
    /* unsigned and unbounded allowed: a mutated input must reach the parser, not stop at
     * its digest */
    pc_options opts = {.max_batch = 8, .flags = PC_LOAD_ALLOW_UNBOUNDED | PC_LOAD_ALLOW_UNSIGNED};
    if (pc_load_memory(data, size, &opts, &m, &err) != PC_OK)
        return 0;
    for (i = 0; i < 5 * 7; i++)
        in[i] = (i % 7 == 3) ? 1.0f : 0.05f * (float)(i % 11);
    (void)pc_run(m, in, 1, out);
    (void)pc_run(m, in, 5, out);
    in[9] = NAN;
    (void)pc_run(m, in, 5, out);
    pc_free(m);
    return 0;
}
