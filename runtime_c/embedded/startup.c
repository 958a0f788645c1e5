/* Bare-metal start-up for the MPS2 AN386 (Cortex-M4F) under QEMU: vector table, reset
 * (FPU on, .data copied, .bss zeroed, stack painted), the newlib system calls the firmware
 * reaches, routed to ARM semihosting, and a fault handler that ends the run with a message
 * instead of hanging the emulator. */
#include "board.h"

#include <errno.h>
#include <stdint.h>
#include <string.h>
#include <sys/stat.h>

extern uint32_t __data_load[], __data_start[], __data_end[], __bss_start[], __bss_end[];
extern uint8_t __heap_start[], __heap_limit[], __stack_limit[], __stack_top[];

int main(void);
void pc_reset_handler(void);
static void fault_handler(void);

#define STACK_PAINT 0xA5u
#define CPACR (*(volatile uint32_t *)0xE000ED88u)

/* ---- semihosting (ARM DUI 0471, "Semihosting operations") ------------------------- */

enum {
    SYS_OPEN = 0x01,
    SYS_WRITE0 = 0x04,
    SYS_WRITE = 0x05,
    SYS_EXIT = 0x18
};
#define ADP_STOPPED_APPLICATION_EXIT 0x20026u
#define ADP_STOPPED_RUNTIME_ERROR 0x20023u

static int semihost(int op, const void *arg)
{
    register int r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

/* Host handles of the semihosting console (":tt" opened for writing is stdout, for
 * appending stderr); -1 until the first write opens them. */
static int host_handle[3] = {-1, -1, -1};

static int console_handle(int fd)
{
    if (host_handle[fd] < 0) {
        const uint32_t args[3] = {(uint32_t)(uintptr_t)":tt", fd == 2 ? 8u : 4u, 3u};
        host_handle[fd] = semihost(SYS_OPEN, args);
    }
    return host_handle[fd];
}

void board_exit(int code)
{
    (void)semihost(SYS_EXIT, (const void *)(uintptr_t)(code == 0 ? ADP_STOPPED_APPLICATION_EXIT
                                                                  : ADP_STOPPED_RUNTIME_ERROR));
    for (;;) {
    }
}

/* ---- memory accounting ------------------------------------------------------------ */

static uint8_t *heap_end = __heap_start;
static size_t heap_peak;

size_t board_heap_peak(void) { return heap_peak; }

size_t board_stack_peak(void)
{
    const uint8_t *p = __stack_limit;
    while (p < __stack_top && *p == STACK_PAINT)
        p++;
    return (size_t)(__stack_top - p);
}

size_t board_stack_size(void) { return (size_t)(__stack_top - __stack_limit); }

/* The link wraps the allocator (-Wl,--wrap=malloc,...) so that "no malloc" is counted, not
 * inferred from the heap's size. */
static size_t allocations;

size_t board_allocations(void) { return allocations; }

void *__real_malloc(size_t size);
void *__real_calloc(size_t n, size_t size);
void *__real_realloc(void *p, size_t size);

void *__wrap_malloc(size_t size)
{
    allocations++;
    return __real_malloc(size);
}

void *__wrap_calloc(size_t n, size_t size)
{
    allocations++;
    return __real_calloc(n, size);
}

void *__wrap_realloc(void *p, size_t size)
{
    allocations++;
    return __real_realloc(p, size);
}

/* ---- newlib system calls ---------------------------------------------------------- */

void *_sbrk(ptrdiff_t incr)
{
    uint8_t *prev = heap_end;
    if (incr > __heap_limit - heap_end || incr < __heap_start - heap_end) {
        errno = ENOMEM;
        return (void *)-1;
    }
    heap_end += incr;
    if ((size_t)(heap_end - __heap_start) > heap_peak)
        heap_peak = (size_t)(heap_end - __heap_start);
    return prev;
}

int _write(int fd, const char *buf, int len)
{
    uint32_t args[3];
    int h;
    if (fd != 1 && fd != 2) {
        errno = EBADF;
        return -1;
    }
    h = console_handle(fd);
    if (h < 0) {
        errno = EIO;
        return -1;
    }
    args[0] = (uint32_t)h;
    args[1] = (uint32_t)(uintptr_t)buf;
    args[2] = (uint32_t)len;
    /* SYS_WRITE returns the number of bytes NOT written. */
    return len - semihost(SYS_WRITE, args);
}

int _read(int fd, char *buf, int len)
{
    (void)fd, (void)buf, (void)len;
    errno = EBADF;
    return -1;
}

int _close(int fd)
{
    (void)fd;
    return 0;
}

int _fstat(int fd, struct stat *st)
{
    (void)fd;
    memset(st, 0, sizeof *st);
    st->st_mode = S_IFCHR;
    return 0;
}

int _isatty(int fd) { return fd >= 0 && fd <= 2; }

int _lseek(int fd, int offset, int whence)
{
    (void)fd, (void)offset, (void)whence;
    errno = ESPIPE;
    return -1;
}

int _getpid(void) { return 1; }

int _kill(int pid, int sig)
{
    (void)pid, (void)sig;
    errno = EINVAL;
    return -1;
}

void _exit(int code) { board_exit(code); }

/* ---- reset and faults ------------------------------------------------------------- */

void pc_reset_handler(void)
{
    uint32_t *src = __data_load, *dst;
    uint8_t *p;
    /* Full access to CP10/CP11 before the first floating-point instruction. */
    CPACR |= 0xFu << 20;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    for (dst = __data_start; dst < __data_end;)
        *dst++ = *src++;
    for (dst = __bss_start; dst < __bss_end;)
        *dst++ = 0;
    /* Paint the stack below this frame so board_stack_peak can find the deepest use. */
    for (p = __stack_limit; p < (uint8_t *)__builtin_frame_address(0) - 64; p++)
        *p = STACK_PAINT;
    board_exit(main());
}

static void fault_handler(void)
{
    (void)semihost(SYS_WRITE0, "fault: HardFault/MemManage/BusFault/UsageFault\n");
    board_exit(1);
}

typedef void (*pc_vector)(void);

/* Initial stack pointer, then the Cortex-M system exceptions; the firmware uses no
 * interrupts, so every other entry is the fault handler too. */
__attribute__((section(".isr_vector"), used)) static const pc_vector vectors[16] = {
    (pc_vector)(uintptr_t)__stack_top, pc_reset_handler, fault_handler, fault_handler,
    fault_handler, fault_handler, fault_handler, 0, 0, 0, 0, fault_handler, fault_handler, 0,
    fault_handler, fault_handler};
