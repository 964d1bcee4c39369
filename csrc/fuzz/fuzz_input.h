/* edgemodbus fuzz harnesses: the contract check and the reader that splits a fuzzer's
 * input into fields.  Shared by every harness (fuzz_codec.c, fuzz_frames.c, fuzz_stream.c,
 * fuzz_serve.c); not part of the module. */
#ifndef EMB_FUZZ_INPUT_H
#define EMB_FUZZ_INPUT_H

#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

#ifndef FUZZ_NAME
#error "define FUZZ_NAME before including fuzz_input.h"
#endif

#define CHECK(cond)                                                                       \
    do {                                                                                  \
        if (!(cond)) {                                                                    \
            fprintf(stderr, FUZZ_NAME ": contract violated at line %d: %s\n", __LINE__,   \
                    #cond);                                                               \
            abort();                                                                      \
        }                                                                                 \
    } while (0)

typedef struct reader {
    const uint8_t *p;
    size_t n;
} reader;

/* The next byte of the input, 0 once it is used up (so every input is a valid one). */
static inline uint8_t rd8(reader *r)
{
    if (r->n == 0)
        return 0;
    r->n--;
    return *r->p++;
}

static inline uint16_t rd16(reader *r)
{
    uint16_t hi = rd8(r);
    return (uint16_t)(hi << 8 | rd8(r));
}

#endif
