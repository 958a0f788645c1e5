/* The firmwares' output without stdio (semihosting writes through startup.c's _write) and
 * their instruction counts (see fw_out.h). */
#include "fw_out.h"

#include "board.h"

#include <string.h>

#define FW_POSE_WIDTH 7

int _write(int fd, const char *buf, int len);

void fw_put(const char *s)
{
    _write(1, s, (int)strlen(s));
}

void fw_put_u(unsigned long v)
{
    char buf[12];
    int i = (int)sizeof buf;
    buf[--i] = '\0';
    do {
        buf[--i] = (char)('0' + v % 10);
        v /= 10;
    } while (v && i > 0);
    fw_put(buf + i);
}

static void put_hex(uint32_t v)
{
    static const char digits[] = "0123456789abcdef";
    char buf[9];
    int i;
    for (i = 7; i >= 0; i--, v >>= 4)
        buf[i] = digits[v & 15];
    buf[8] = '\0';
    fw_put(buf);
}

void fw_put_kv(const char *key, unsigned long v)
{
    fw_put(" ");
    fw_put(key);
    fw_put("=");
    fw_put_u(v);
}

void fw_put_pose(const char *impl, unsigned k, const float *p)
{
    int j;
    fw_put("out ");
    fw_put(impl);
    fw_put(" ");
    fw_put_u(k);
    for (j = 0; j < FW_POSE_WIDTH; j++) {
        uint32_t bits;
        memcpy(&bits, &p[j], 4);
        fw_put(" ");
        put_hex(bits);
    }
    fw_put("\n");
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
uint32_t fw_ticks_now(void)
{
    return SYST_CVR;
}

uint32_t fw_ticks_since(uint32_t start)
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
    ticks = fw_ticks_since(t);
    return ticks ? (unsigned long)(4ull * CALIBRATION_ITERATIONS * 1000u / ticks) : 0;
}

unsigned long fw_count_start(void)
{
    unsigned long per_tick;
    systick_start();
    per_tick = calibrate();
    fw_put("calibration instructions_per_tick_x1000=");
    fw_put_u(per_tick);
    fw_put("\n");
    return per_tick;
}

void fw_report_count(const char *impl, uint32_t ticks, unsigned long per_tick_milli,
                     unsigned long poses)
{
    fw_put("count ");
    fw_put(impl);
    fw_put_kv("instructions_per_pose",
              (unsigned long)((unsigned long long)ticks * per_tick_milli / 1000u / poses));
    fw_put_kv("ticks", ticks);
    fw_put_kv("poses", poses);
    fw_put("\n");
}

void fw_put_memory(void)
{
    fw_put("mallocs=");
    fw_put_u(board_allocations());
    fw_put_kv("stack_peak", board_stack_peak());
    fw_put_kv("stack_reserved", board_stack_size());
    fw_put("\n");
}

void fw_count(const char *impl, int (*run)(const float *, float *), const float (*poses)[7],
              unsigned n, unsigned runs, unsigned long per_tick_milli)
{
    float out[FW_POSE_WIDTH];
    uint32_t t;
    unsigned r, k;
    for (k = 0; k < n; k++) {
        if (run(poses[k], out) != 0) {
            fw_put(impl);
            fw_put(" failed\n");
            board_exit(1);
        }
        fw_put_pose(impl, k, out);
    }
    t = fw_ticks_now();
    for (r = 0; r < runs; r++)
        for (k = 0; k < n; k++)
            run(poses[k], out);
    fw_report_count(impl, fw_ticks_since(t), per_tick_milli, (unsigned long)runs * n);
}
