/* edgemodbus: read a block and decode it in one C call (the polling hot path). */
#ifndef EMB_POLL_H
#define EMB_POLL_H

#include "emb_codec.h"
#include "emb_io.h"

long emb_read_decode(modbus_t *ctx, emb_link *lk, int slave, int function, int addr, int nb,
                     void *dest, uint8_t *rsp, emb_plan *plan, int mode);

#endif
