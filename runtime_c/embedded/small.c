/* Firmware for a small board: the model in flash, read in place (PC_LOAD_IN_PLACE), loaded
 * with pc_load_into into a static arena, one pose at a time (max_batch 1). No stdio and no
 * heap: output goes through semihosting writes (startup.c's _write), malloc calls are
 * counted by the linker's --wrap and must stay 0. The linker script gives the board its
 * RAM (16 KB or 32 KB, stack included): a firmware that does not fit does not link.
 *
 * It prints, in lines the report and the tests parse:
 *   load ok arena_reserved=N arena_used=N steps=N
 *   out input K h0 .. h6             (pose K as float32 bit patterns)
 *   out pc_run K h0 .. h6            (its correction)
 *   out reference K ...  / out emlearn K ...   (MLP builds: FW_HAND, FW_EMLEARN)
 *   count IMPL instructions_per_pose=N ticks=N poses=N
 *   mallocs=N stack_peak=N stack_reserved=N
 *
 * (output and instruction counts: fw_out.h) */
#include "board.h"
#include "fw_out.h"
#include "poses.h"
#include "posecorr.h"

#include <stdint.h>
#include <string.h>

#if defined(FW_HAND) || defined(FW_EMLEARN)
#include "fw_impls.h"
#endif

extern const unsigned char pc_fw_model[];
extern const unsigned long pc_fw_model_size;

#ifndef FW_ARENA_BYTES
#define FW_ARENA_BYTES 12288u
#endif
#ifndef FW_PROGRAM_OPS
#define FW_PROGRAM_OPS 32
#endif
#ifndef FW_COUNT_RUNS
#define FW_COUNT_RUNS 4
#endif
#define FW_COUNTED_POSES ((unsigned long)FW_COUNT_RUNS * PC_FW_N_POSES)

static unsigned char fw_arena[FW_ARENA_BYTES] __attribute__((aligned(8)));

int main(void)
{
    float out[1][PC_POSE_WIDTH];
    pc_options opts;
    pc_model *model;
    pc_error err;
    unsigned long per_tick;
    uint32_t t, r;
    unsigned k;

    memset(&opts, 0, sizeof opts);
    opts.max_batch = 1;
    opts.flags = PC_LOAD_IN_PLACE | PC_LOAD_NO_METADATA;
    opts.program_ops = FW_PROGRAM_OPS;
    if (pc_load_into(pc_fw_model, pc_fw_model_size, &opts, fw_arena, sizeof fw_arena, &model,
                     &err) != PC_OK) {
        fw_put("load failed: ");
        fw_put(err.message);
        fw_put("\n");
        board_exit(1);
    }
    fw_put("load ok");
    fw_put_kv("arena_reserved", sizeof fw_arena);
    fw_put_kv("arena_used", pc_arena_bytes(model));
    fw_put_kv("steps", pc_step_count(model));
    fw_put_kv("program_ops", FW_PROGRAM_OPS);
    fw_put("\n");
    for (k = 0; k < PC_FW_N_POSES; k++)
        fw_put_pose("input", k, pc_fw_poses[k]);
    for (k = 0; k < PC_FW_N_POSES; k++) {
        if (pc_run(model, pc_fw_poses[k], 1, out[0]) != PC_OK) {
            fw_put("run failed: ");
            fw_put(pc_model_message(model));
            fw_put("\n");
            board_exit(1);
        }
        fw_put_pose("pc_run", k, out[0]);
    }

    per_tick = fw_count_start();
    t = fw_ticks_now();
    for (r = 0; r < FW_COUNT_RUNS; r++)
        for (k = 0; k < PC_FW_N_POSES; k++)
            pc_run(model, pc_fw_poses[k], 1, out[0]);
    fw_report_count("pc_run", fw_ticks_since(t), per_tick, FW_COUNTED_POSES);

#ifdef FW_HAND
    fw_count("reference", fw_hand, pc_fw_poses, PC_FW_N_POSES, FW_COUNT_RUNS, per_tick);
#endif
#ifdef FW_EMLEARN
    fw_emlearn_setup();
    fw_count("emlearn", fw_emlearn, pc_fw_poses, PC_FW_N_POSES, FW_COUNT_RUNS, per_tick);
#endif

    fw_put_memory();
    board_exit(0);
}
