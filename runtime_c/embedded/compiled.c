/* Firmware for a 2 KB board: one model compiled to C by `posecorr compile` (the Makefile
 * writes it from the zhou MLP: pc_fw_compiled_run), no runtime, no arena, no heap. It
 * corrects the poses of poses.h one at a time and prints, in the lines small_report.py
 * parses (fw_out.h):
 *   out input K h0 .. h6      (pose K as float32 bit patterns)
 *   out compiled K h0 .. h6   (its correction)
 *   count compiled instructions_per_pose=N ticks=N poses=N
 *   mallocs=N stack_peak=N stack_reserved=N
 * The host compares the corrections with pc_run's bit for bit. */
#include "board.h"
#include "fw_out.h"
#include "poses.h"

#ifndef FW_COUNT_RUNS
#define FW_COUNT_RUNS 4
#endif

int pc_fw_compiled_run(const float in[7], float out[7]);

int main(void)
{
    float out[7];
    unsigned long per_tick;
    uint32_t t, r;
    unsigned k;

    for (k = 0; k < PC_FW_N_POSES; k++)
        fw_put_pose("input", k, pc_fw_poses[k]);
    for (k = 0; k < PC_FW_N_POSES; k++) {
        if (pc_fw_compiled_run(pc_fw_poses[k], out) != 0) {
            fw_put("run failed: an output is not finite\n");
            board_exit(1);
        }
        fw_put_pose("compiled", k, out);
    }
    per_tick = fw_count_start();
    t = fw_ticks_now();
    for (r = 0; r < FW_COUNT_RUNS; r++)
        for (k = 0; k < PC_FW_N_POSES; k++)
            pc_fw_compiled_run(pc_fw_poses[k], out);
    fw_report_count("compiled", fw_ticks_since(t), per_tick,
                    (unsigned long)FW_COUNT_RUNS * PC_FW_N_POSES);
    fw_put_memory();
    board_exit(0);
}
