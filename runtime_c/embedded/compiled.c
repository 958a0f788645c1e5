/* Firmware for a 2 KB board: one model's one-pose function, no runtime, no arena, no heap.
 * By default the function `posecorr compile` wrote (pc_fw_compiled_run); with FW_HAND the
 * hand-written function of the same MLP, with FW_EMLEARN emlearn's eml_net of it (fw_impls.h),
 * so that each is counted with the RAM it needs. It corrects the poses of poses.h one at a
 * time and prints, in the lines small_report.py parses (fw_out.h):
 *   out input K h0 .. h6      (pose K as float32 bit patterns)
 *   out IMPL K h0 .. h6       (its correction; IMPL compiled, reference or emlearn)
 *   count IMPL instructions_per_pose=N ticks=N poses=N
 *   mallocs=N stack_peak=N stack_reserved=N
 * The host compares the corrections with pc_run's. */
#include "board.h"
#include "fw_out.h"
#include "poses.h"

#ifndef FW_COUNT_RUNS
#define FW_COUNT_RUNS 4
#endif

#if defined(FW_HAND) || defined(FW_EMLEARN)
#include "fw_impls.h"
#endif
#if defined(FW_HAND)
#define FW_IMPL "reference"
#define FW_RUN fw_hand
#elif defined(FW_EMLEARN)
#define FW_IMPL "emlearn"
#define FW_RUN fw_emlearn
#else
#define FW_IMPL "compiled"
#define FW_RUN pc_fw_compiled_run
int pc_fw_compiled_run(const float in[7], float out[7]);
#endif

int main(void)
{
    unsigned long per_tick;
    unsigned k;

    for (k = 0; k < PC_FW_N_POSES; k++)
        fw_put_pose("input", k, pc_fw_poses[k]);
#if defined(FW_EMLEARN) && !defined(FW_HAND)
    fw_emlearn_setup();
#endif
    per_tick = fw_count_start();
    fw_count(FW_IMPL, FW_RUN, pc_fw_poses, PC_FW_N_POSES, FW_COUNT_RUNS, per_tick);
    fw_put_memory();
    board_exit(0);
}
