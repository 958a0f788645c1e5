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
 *   out reference K ...  / out emlearn K ...   (zhou MLP builds)
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

#ifdef FW_ZHOU
#include "zhou_reference.h"
extern const pc_zhou_weights *const pc_fw_zhou;
#endif
#ifdef FW_EMLEARN
#include "eml_net.h"
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

#ifdef FW_EMLEARN
/* The zhou MLP's four hidden layers and its output layer, in emlearn's structures, over
 * the same weights (emlearn reads W[i][o] at o + i * n_outputs, the exporter's layout). */
static float eml_buffer1[PC_ZHOU_HIDDEN], eml_buffer2[PC_ZHOU_HIDDEN];
static EmlNetLayer eml_layers[PC_ZHOU_LAYERS];
static EmlNet eml_model = {PC_ZHOU_LAYERS, eml_layers, eml_buffer1, eml_buffer2, PC_ZHOU_HIDDEN};

static void eml_setup(const pc_zhou_weights *w)
{
    int l;
    eml_layers[0] = (EmlNetLayer){PC_ZHOU_HIDDEN, PC_ZHOU_IN, w->w_in, w->b_in,
                                  EmlNetActivationTanh};
    for (l = 0; l < PC_ZHOU_LAYERS - 2; l++)
        eml_layers[l + 1] = (EmlNetLayer){PC_ZHOU_HIDDEN, PC_ZHOU_HIDDEN, w->w_hidden[l],
                                          w->b_hidden[l], EmlNetActivationTanh};
    eml_layers[PC_ZHOU_LAYERS - 1] = (EmlNetLayer){PC_ZHOU_IN, PC_ZHOU_HIDDEN, w->w_out,
                                                   w->b_out, EmlNetActivationIdentity};
}

static int eml_pose(const pc_zhou_weights *w, const float *in, float *out)
{
    float x[PC_ZHOU_IN], y[PC_ZHOU_IN];
    pc_zhou_encode(w, in, x);
    if (eml_net_regress(&eml_model, x, PC_ZHOU_IN, y, PC_ZHOU_IN) != EmlOk)
        return 0;
    pc_zhou_decode(w, y, out);
    return 1;
}
#endif

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

#ifdef FW_ZHOU
    for (k = 0; k < PC_FW_N_POSES; k++) {
        pc_zhou_reference(pc_fw_zhou, pc_fw_poses[k], out[0]);
        fw_put_pose("reference", k, out[0]);
    }
    t = fw_ticks_now();
    for (r = 0; r < FW_COUNT_RUNS; r++)
        for (k = 0; k < PC_FW_N_POSES; k++)
            pc_zhou_reference(pc_fw_zhou, pc_fw_poses[k], out[0]);
    fw_report_count("reference", fw_ticks_since(t), per_tick, FW_COUNTED_POSES);
#endif
#ifdef FW_EMLEARN
    eml_setup(pc_fw_zhou);
    for (k = 0; k < PC_FW_N_POSES; k++) {
        if (!eml_pose(pc_fw_zhou, pc_fw_poses[k], out[0]))
            board_exit(1);
        fw_put_pose("emlearn", k, out[0]);
    }
    t = fw_ticks_now();
    for (r = 0; r < FW_COUNT_RUNS; r++)
        for (k = 0; k < PC_FW_N_POSES; k++)
            eml_pose(pc_fw_zhou, pc_fw_poses[k], out[0]);
    fw_report_count("emlearn", fw_ticks_since(t), per_tick, FW_COUNTED_POSES);
#endif

    fw_put_memory();
    board_exit(0);
}
