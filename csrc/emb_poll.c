/* edgemodbus: one C call per polled block.
 *
 * A poll step reads a block and decodes it through the block's compiled plan; doing both
 * here saves the bus worker a second trip through Python and the GIL per block, which is
 * most of what it spends on a block whose values did not change. */
#include "emb_poll.h"

/* emb_read() then emb_decode(): the number of items the decode reports (see
 * emb_decode), or -1 with errno set when the read failed (nothing is decoded then). */
long emb_read_decode(modbus_t *ctx, emb_link *lk, int slave, int function, int addr, int nb,
                     void *dest, uint8_t *rsp, emb_plan *plan, int mode)
{
    int rc = emb_read(ctx, lk, slave, function, addr, nb, dest, rsp);

    if (rc == -1)
        return -1;
    return emb_decode(plan, dest, (uint32_t)rc, mode);
}
