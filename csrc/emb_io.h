/* edgemodbus: one C call per Modbus transaction (and per line clean-up), so that a bus
 * worker re-takes the GIL once per request instead of once per libmodbus call. */
#ifndef EMB_IO_H
#define EMB_IO_H

#include <stdint.h>
#include <modbus.h>

#include "emb_check.h"  /* the EMB_E* errnos */
#include "emb_link.h"
#include "emb_stream.h" /* emb_report_take */
#include "emb_util.h"   /* emb_discard_input, emb_now_ns */

int emb_read(modbus_t *ctx, emb_link *lk, int slave, int function, int addr, int nb,
             void *dest, uint8_t *rsp);
int emb_transact(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                 uint8_t *rsp);
int emb_send(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len);
int emb_request(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                int timeout_ms, uint8_t *rsp);
int emb_write_pdu(int function, int addr, int nb, const uint16_t *values, uint8_t *pdu);
int emb_write(modbus_t *ctx, emb_link *lk, int slave, int function, int addr, int nb,
              const uint16_t *values, int timeout_ms, uint8_t *req, uint8_t *rsp);
long emb_link_discard(modbus_t *ctx, emb_link *lk, int total_ms, int quiet_ms, int limit_ms);
long emb_pump(modbus_t *ctx, emb_link *lk);
long emb_feed(emb_link *lk, const uint8_t *data, int n);
int emb_echo_seen(int err, const uint8_t *rsp, int got, const uint8_t *sent, int sent_len);
void emb_trace_put(emb_link *lk, int direction, const uint8_t *frame, int n);
int emb_trace_take(emb_trace *t, uint8_t *out, int *direction, int64_t *t_ns);

#endif
