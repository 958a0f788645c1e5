/* print_shapes MODEL...: loads each model with the default options, and again with the
 * program_ops of the small boards' firmware (runtime_c/embedded/Makefile, SMALL16_OPS: its
 * programs are chunks of the default ones), and prints the shape of every one-pose program
 * the loader builds ("shape <hex>", one line each). Linked with the library's sources built
 * with PC_PRINT_SHAPES, which call the two functions below; tools/compile_programs.py turns
 * the lines into programs_compiled.c. */
#include "posecorr.h"

#include <stdio.h>
#include <string.h>

/* program_ops of each load: the default, and the small boards' */
static const size_t g_program_ops[] = {0, 32};

static int g_line_open;

void pc_print_shape_byte(unsigned byte);
void pc_print_shape_end(void);

void pc_print_shape_byte(unsigned byte)
{
    if (!g_line_open)
        fputs("shape ", stdout);
    g_line_open = 1;
    printf("%02x", byte);
}

void pc_print_shape_end(void)
{
    if (g_line_open)
        putchar('\n');
    g_line_open = 0;
}

int main(int argc, char **argv)
{
    int i;
    size_t k;
    for (i = 1; i < argc; i++)
        for (k = 0; k < sizeof g_program_ops / sizeof g_program_ops[0]; k++) {
            pc_model *model;
            pc_error err;
            pc_options opts;
            memset(&opts, 0, sizeof opts);
            opts.program_ops = g_program_ops[k];
            if (pc_load_file(argv[i], &opts, &model, &err) != PC_OK) {
                fprintf(stderr, "%s: %s\n", argv[i], err.message);
                return 1;
            }
            pc_free(model);
        }
    return 0;
}
