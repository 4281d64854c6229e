/* What startup.c gives the test program: semihosting output and exit, and the stack high-water mark. */
#ifndef STARTUP_H
#define STARTUP_H

#include <stdint.h>

void semihost_write0(const char *text);
void semihost_exit(int ok);
uint32_t stack_bytes_used(void);

#endif
