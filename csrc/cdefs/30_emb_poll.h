/* csrc/emb_poll.h, for cffi. */
long emb_read_decode(modbus_t *ctx, emb_link *lk, int slave, int function, int addr, int nb,
                     void *dest, uint8_t *rsp, emb_plan *plan, int mode);
