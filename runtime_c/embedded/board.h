/* What startup.c offers the firmware: the end of the run and its memory figures. */
#ifndef PC_EMBEDDED_BOARD_H
#define PC_EMBEDDED_BOARD_H

#include <stddef.h>

/* Ends the QEMU run: exit status 0 for code 0, 1 otherwise (semihosting SYS_EXIT). */
void board_exit(int code) __attribute__((noreturn));
/* Highest heap break reached through _sbrk (bytes above the end of .bss). */
size_t board_heap_peak(void);
/* Deepest stack use so far (bytes below the top of RAM that are no longer painted). */
size_t board_stack_peak(void);
size_t board_stack_size(void);
/* Calls of malloc, calloc and realloc so far (newlib's own included). */
size_t board_allocations(void);

#endif
