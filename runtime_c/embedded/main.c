/* posecorr on a Cortex-M4F: loads the corrector embedded in flash (model_data.c, made by
 * embed.py from the .onnx file), corrects the poses of poses.h one at a time (the
 * tracker-rate path) and all at once (the batch plan), and prints inputs and outputs as
 * float32 bit patterns over semihosting so the host can compare them exactly with the
 * x86 runtime. Exit status 0 only when every call returned PC_OK and both paths agree
 * bit for bit. */
#include "board.h"
#include "poses.h"
#include "posecorr.h"

#include <malloc.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

extern const unsigned char pc_fw_model[];
extern const unsigned long pc_fw_model_size;

/* Runtimes from 0.2.0 on load into a caller-provided arena without malloc; the firmware
 * uses that when the header offers it, pc_load_memory (newlib's malloc) otherwise. */
#if defined(PC_VERSION_NUMBER) && PC_VERSION_NUMBER >= 200
#define FW_LOAD_INTO 1
#ifndef FW_ARENA_BYTES
#define FW_ARENA_BYTES (384u * 1024u)
#endif
/* A product sizes it from pc_required_bytes; in its own section so the map shows it apart
 * from .bss. */
static unsigned char fw_arena[FW_ARENA_BYTES] __attribute__((aligned(8), section(".arena")));
#endif

/* Plans for 1 and FW_MAX_BATCH poses (the Makefile's, 16 by default): the firmware never
 * runs more at once, and the arena grows with the largest plan. */
#ifndef FW_MAX_BATCH
#define FW_MAX_BATCH 16
#endif
/* pc_options.flags and program_ops (posecorr.h); the model lies in flash for good, so its
 * weights can be read there. */
#ifndef FW_LOAD_FLAGS
#define FW_LOAD_FLAGS PC_LOAD_IN_PLACE
#endif
#ifndef FW_PROGRAM_OPS
#define FW_PROGRAM_OPS 0
#endif

static unsigned long bits(float f)
{
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return (unsigned long)u;
}

static void print_row(const char *label, const float *row)
{
    int j;
    printf(" %s", label);
    for (j = 0; j < PC_POSE_WIDTH; j++)
        printf(" %08lx", bits(row[j]));
}

static pc_status load(unsigned long size, const pc_options *opts, pc_model **model,
                      pc_error *err)
{
#ifdef FW_LOAD_INTO
    return pc_load_into(pc_fw_model, size, opts, fw_arena, sizeof fw_arena, model, err);
#else
    return pc_load_memory(pc_fw_model, size, opts, model, err);
#endif
}

int main(void)
{
    static float single[PC_FW_N_POSES][PC_POSE_WIDTH], batch[PC_FW_N_POSES][PC_POSE_WIDTH];
    pc_options opts;
    pc_model *model;
    pc_error err;
    pc_status st;
    struct mallinfo before_load, after_load;
    size_t allocations;
    size_t i, n_ok = 0;
    int same;

    memset(&opts, 0, sizeof opts); /* fields added by later versions keep their defaults */
    opts.max_batch = FW_MAX_BATCH;
    opts.flags = FW_LOAD_FLAGS;
    opts.program_ops = FW_PROGRAM_OPS;
#ifdef FW_LOAD_INTO
    printf("api: pc_load_into arena_reserved=%lu version=%d header=%d\n",
           (unsigned long)sizeof fw_arena, pc_version(), PC_VERSION_NUMBER);
    if (pc_version() != PC_VERSION_NUMBER)
        return 1;
#else
    printf("api: pc_load_memory\n");
#endif
    /* The error path on the target: half the file must be refused with the message the
     * host gives (the host compares the two). */
    st = load(pc_fw_model_size / 2, &opts, &model, &err);
    printf("truncated: %s: %s\n", pc_status_name(st), err.message);
    before_load = mallinfo(); /* after the first printf: stdout's buffer is not the model's */
    allocations = board_allocations();
    st = load(pc_fw_model_size, &opts, &model, &err);
    if (st != PC_OK) {
        printf("load: %s: %s\n", pc_status_name(st), err.message);
        return 1;
    }
    allocations = board_allocations() - allocations;
    after_load = mallinfo();
    printf("load: ok model_bytes=%lu nodes=%lu steps=%lu arena_bytes=%lu max_batch=%lu\n",
           pc_fw_model_size, (unsigned long)pc_node_count(model),
           (unsigned long)pc_step_count(model), (unsigned long)pc_arena_bytes(model),
           (unsigned long)pc_max_batch(model));
    printf("heap: load_allocations=%lu model_in_use=%lu peak_during_load=%lu\n",
           (unsigned long)allocations,
           (unsigned long)(after_load.uordblks - before_load.uordblks),
           (unsigned long)board_heap_peak());

    for (i = 0; i < PC_FW_N_POSES; i++) {
        st = pc_run(model, pc_fw_poses[i], 1, single[i]);
        if (st != PC_OK)
            printf("run: pose %lu: %s: %s\n", (unsigned long)i, pc_status_name(st),
                   pc_model_message(model));
        else
            n_ok++;
    }
    st = pc_run(model, &pc_fw_poses[0][0], PC_FW_N_POSES, &batch[0][0]);
    if (st != PC_OK)
        printf("run: batch of %d: %s: %s\n", PC_FW_N_POSES, pc_status_name(st),
               pc_model_message(model));
    same = st == PC_OK && memcmp(single, batch, sizeof single) == 0;

    for (i = 0; i < PC_FW_N_POSES; i++) {
        printf("pose %lu", (unsigned long)i);
        print_row("in", pc_fw_poses[i]);
        print_row("out", single[i]);
        printf("\n");
    }
    printf("batch: %s\n", same ? "identical to single-pose runs" : "DIFFERS from single-pose runs");
    pc_free(model);
#ifdef FW_LOAD_INTO
    {
        /* Last, because it allocates: the figure a product would size fw_arena from. */
        size_t need = 0;
        st = pc_required_bytes(pc_fw_model, pc_fw_model_size, &opts, &need, &err);
        printf("arena: required_bytes=%lu (%s)\n", (unsigned long)need, pc_status_name(st));
    }
#endif
    printf("memory: heap_peak=%lu stack_peak=%lu stack_reserved=%lu\n",
           (unsigned long)board_heap_peak(), (unsigned long)board_stack_peak(),
           (unsigned long)board_stack_size());
    printf("done: %lu/%d poses ok\n", (unsigned long)n_ok, PC_FW_N_POSES);
    fflush(stdout);
    return n_ok == PC_FW_N_POSES && same ? 0 : 1;
}
