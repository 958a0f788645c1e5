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
 *   count IMPL instructions_per_pose=N ticks=N runs=N
 *   mallocs=N stack_peak=N stack_reserved=N
 *
 * Instructions are counted under `qemu-system-arm -icount shift=0`, where virtual time
 * advances one nanosecond per instruction: SysTick, clocked from the processor clock,
 * advances one tick per fixed number of nanoseconds, calibrated here against a loop of a
 * known number of instructions (the figure is printed: "calibration"). */
#include "board.h"
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

static unsigned char fw_arena[FW_ARENA_BYTES] __attribute__((aligned(8)));

int _write(int fd, const char *buf, int len);

/* ---- output without stdio ------------------------------------------------------------ */

static void put(const char *s)
{
    _write(1, s, (int)strlen(s));
}

static void put_u(unsigned long v)
{
    char buf[12];
    int i = (int)sizeof buf;
    buf[--i] = '\0';
    do {
        buf[--i] = (char)('0' + v % 10);
        v /= 10;
    } while (v && i > 0);
    put(buf + i);
}

static void put_hex(uint32_t v)
{
    static const char digits[] = "0123456789abcdef";
    char buf[9];
    int i;
    for (i = 7; i >= 0; i--, v >>= 4)
        buf[i] = digits[v & 15];
    buf[8] = '\0';
    put(buf);
}

static void put_kv(const char *key, unsigned long v)
{
    put(" ");
    put(key);
    put("=");
    put_u(v);
}

static void put_pose(const char *impl, unsigned k, const float *p)
{
    int j;
    put("out ");
    put(impl);
    put(" ");
    put_u(k);
    for (j = 0; j < PC_POSE_WIDTH; j++) {
        uint32_t bits;
        memcpy(&bits, &p[j], 4);
        put(" ");
        put_hex(bits);
    }
    put("\n");
}

/* ---- instruction counts ----------------------------------------------------------------- */

#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)

static void systick_start(void)
{
    SYST_RVR = 0x00FFFFFFu;
    SYST_CVR = 0;
    SYST_CSR = 5u; /* enabled, processor clock, no interrupt */
}

/* SysTick counts down through 24 bits. */
static uint32_t ticks_since(uint32_t start)
{
    return (start - SYST_CVR) & 0x00FFFFFFu;
}

/* 4 instructions per iteration (subs, bne, and two nops) */
static void __attribute__((noinline)) known_loop(uint32_t n)
{
    __asm__ volatile("1: nop\n nop\n subs %0, %0, #1\n bne 1b" : "+r"(n) : : "cc");
}

#define CALIBRATION_ITERATIONS 250000u

/* Instructions per SysTick tick, x 1000. */
static unsigned long calibrate(void)
{
    uint32_t t = SYST_CVR, ticks;
    known_loop(CALIBRATION_ITERATIONS);
    ticks = ticks_since(t);
    return ticks ? (unsigned long)(4ull * CALIBRATION_ITERATIONS * 1000u / ticks) : 0;
}

static void report_count(const char *impl, uint32_t ticks, unsigned long per_tick_milli)
{
    const unsigned long poses = (unsigned long)FW_COUNT_RUNS * PC_FW_N_POSES;
    put("count ");
    put(impl);
    put_kv("instructions_per_pose",
           (unsigned long)((unsigned long long)ticks * per_tick_milli / 1000u / poses));
    put_kv("ticks", ticks);
    put_kv("poses", poses);
    put("\n");
}

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
        put("load failed: ");
        put(err.message);
        put("\n");
        board_exit(1);
    }
    put("load ok");
    put_kv("arena_reserved", sizeof fw_arena);
    put_kv("arena_used", pc_arena_bytes(model));
    put_kv("steps", pc_step_count(model));
    put_kv("program_ops", FW_PROGRAM_OPS);
    put("\n");
    for (k = 0; k < PC_FW_N_POSES; k++)
        put_pose("input", k, pc_fw_poses[k]);
    for (k = 0; k < PC_FW_N_POSES; k++) {
        if (pc_run(model, pc_fw_poses[k], 1, out[0]) != PC_OK) {
            put("run failed: ");
            put(pc_model_message(model));
            put("\n");
            board_exit(1);
        }
        put_pose("pc_run", k, out[0]);
    }

    systick_start();
    per_tick = calibrate();
    put("calibration instructions_per_tick_x1000=");
    put_u(per_tick);
    put("\n");
    t = SYST_CVR;
    for (r = 0; r < FW_COUNT_RUNS; r++)
        for (k = 0; k < PC_FW_N_POSES; k++)
            pc_run(model, pc_fw_poses[k], 1, out[0]);
    report_count("pc_run", ticks_since(t), per_tick);

#ifdef FW_ZHOU
    for (k = 0; k < PC_FW_N_POSES; k++) {
        pc_zhou_reference(pc_fw_zhou, pc_fw_poses[k], out[0]);
        put_pose("reference", k, out[0]);
    }
    t = SYST_CVR;
    for (r = 0; r < FW_COUNT_RUNS; r++)
        for (k = 0; k < PC_FW_N_POSES; k++)
            pc_zhou_reference(pc_fw_zhou, pc_fw_poses[k], out[0]);
    report_count("reference", ticks_since(t), per_tick);
#endif
#ifdef FW_EMLEARN
    eml_setup(pc_fw_zhou);
    for (k = 0; k < PC_FW_N_POSES; k++) {
        if (!eml_pose(pc_fw_zhou, pc_fw_poses[k], out[0]))
            board_exit(1);
        put_pose("emlearn", k, out[0]);
    }
    t = SYST_CVR;
    for (r = 0; r < FW_COUNT_RUNS; r++)
        for (k = 0; k < PC_FW_N_POSES; k++)
            eml_pose(pc_fw_zhou, pc_fw_poses[k], out[0]);
    report_count("emlearn", ticks_since(t), per_tick);
#endif

    put("mallocs=");
    put_u(board_allocations());
    put_kv("stack_peak", board_stack_peak());
    put_kv("stack_reserved", board_stack_size());
    put("\n");
    board_exit(0);
}
