/* edgemodbus: the link kinds of csrc/emb_rtu.c: plain RTU (a serial port, or RTU frames
 * over a socket) and Modbus TCP (MBAP).  emb_rtu_frame and emb_rtu_send are shared with
 * the DTU streams of csrc/emb_stream.c. */
#ifndef EMB_RTU_H
#define EMB_RTU_H

#include "emb_backend.h"

extern const emb_backend emb_rtu_backend;
extern const emb_backend emb_mbap_backend;

int emb_rtu_frame(int slave, const uint8_t *pdu, int pdu_len, uint8_t *sent, int *sent_len);
int emb_rtu_send(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                 uint8_t *sent, int *sent_len);

#endif
