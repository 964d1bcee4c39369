/* edgemodbus: what csrc/emb_io.c (transactions, the reply reader) and csrc/emb_stream.c
 * (DTU streams: heartbeats, wrapped frames, the report ring) share.  Internal: not in
 * the cdefs. */
#ifndef EMB_WIRE_H
#define EMB_WIRE_H

#include <stdint.h>
#include <modbus.h>

#include "emb_io.h"

#define EMB_MAX_ADU 260 /* MODBUS_TCP_MAX_ADU_LENGTH: rsp holds at least this much */
#define EMB_MAX_RTU 256 /* an RTU ADU: address + PDU + CRC (Modbus over Serial Line 2.5.1) */
#define EMB_MBAP 7      /* MBAP header (Modbus Messaging on TCP/IP v1.0b, 3.1.3) */

/* emb_io.c */
uint16_t emb_crc16(const uint8_t *p, int n);
int64_t emb_clock_ns(void);
int emb_wait_until(int fd, int64_t deadline_ns);
int emb_eof_errno(int fd);
int emb_pending(int fd);
int emb_reply_length(const uint8_t *p, int got, int mbap);

/* emb_stream.c: the transaction steps of a stream link (emb_is_stream) */
int emb_is_stream(const emb_link *lk);
int emb_stream_drop_pending(emb_link *lk, int fd);
int emb_stream_skip_echo(emb_link *lk, int fd, const uint8_t *sent, int sent_len,
                         int first_ms, int byte_ms);
int emb_stream_recv_frame(emb_link *lk, int fd, int slave, int first_ms, int byte_ms,
                          uint8_t *rsp, int *got);
int emb_stream_pending(emb_link *lk, int fd);
int emb_stream_recv_wrapped(emb_link *lk, int fd, int slave, const uint8_t *pdu, int count,
                            int first_ms, uint8_t *rsp);
long emb_stream_discard(emb_link *lk, int fd, int total_ms, int quiet_ms, int limit_ms);

#endif
