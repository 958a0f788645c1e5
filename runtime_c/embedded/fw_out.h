/* What the small boards' firmwares (small.c, compiled.c) share: output without stdio, in
 * the lines small_report.py parses, and instruction counts.
 *
 * Instructions are counted under `qemu-system-arm -icount shift=0`, where virtual time
 * advances one nanosecond per instruction: SysTick, clocked from the processor clock,
 * advances one tick per fixed number of nanoseconds, calibrated against a loop of a known
 * number of instructions (the figure is printed: "calibration"). */
#ifndef PC_EMBEDDED_FW_OUT_H
#define PC_EMBEDDED_FW_OUT_H

#include <stdint.h>

void fw_put(const char *s);
void fw_put_u(unsigned long v);
/* " key=v" */
void fw_put_kv(const char *key, unsigned long v);
/* "out IMPL K h0 .. h6": pose K as float32 bit patterns */
void fw_put_pose(const char *impl, unsigned k, const float *p);
/* "mallocs=N stack_peak=N stack_reserved=N" (board.h's figures so far) */
void fw_put_memory(void);

/* Starts SysTick and prints its calibration; returns instructions per tick x 1000. */
unsigned long fw_count_start(void);
uint32_t fw_ticks_now(void);
uint32_t fw_ticks_since(uint32_t start);
/* "count IMPL instructions_per_pose=N ticks=N poses=N" for `poses` poses in `ticks`. */
void fw_report_count(const char *impl, uint32_t ticks, unsigned long per_tick_milli,
                     unsigned long poses);
/* Corrects the n poses with `run` ("out IMPL K ..." lines; exit 1 if it fails), then counts
 * its instructions over `runs` passes ("count IMPL ..."). */
void fw_count(const char *impl, int (*run)(const float *, float *), const float (*poses)[7],
              unsigned n, unsigned runs, unsigned long per_tick_milli);

#endif
