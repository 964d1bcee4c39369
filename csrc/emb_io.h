/* edgemodbus: one C call per Modbus transaction (and per line clean-up), so that a bus
 * worker re-takes the GIL once per request instead of once per libmodbus call. */
#ifndef EMB_IO_H
#define EMB_IO_H

#include <stdint.h>
#include <modbus.h>

int emb_read(modbus_t *ctx, int slave, int function, int addr, int nb, void *dest);
int emb_transact_raw(modbus_t *ctx, int slave, const uint8_t *req, int req_len, uint8_t *rsp);
int emb_send_raw(modbus_t *ctx, int slave, const uint8_t *req, int req_len);
long emb_discard_input(int fd, int total_ms, int quiet_ms);

#endif
