/* csrc/emb_io.h, for cffi.  All return -1 with errno set on failure. */
int emb_read(modbus_t *ctx, int slave, int function, int addr, int nb, void *dest);
int emb_transact_raw(modbus_t *ctx, int slave, const uint8_t *req, int req_len, uint8_t *rsp);
int emb_send_raw(modbus_t *ctx, int slave, const uint8_t *req, int req_len);
long emb_discard_input(int fd, int total_ms, int quiet_ms);
