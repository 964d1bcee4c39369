/* edgemodbus: the DTU stream link kinds of csrc/emb_stream.c (heartbeats, wrapped report
 * frames) and their report ring. */
#ifndef EMB_STREAM_H
#define EMB_STREAM_H

#include "emb_backend.h"

extern const emb_backend emb_stream_backend;
extern const emb_backend emb_wrapped_backend;

#define EMB_STREAM_MORE (-2) /* emb_stream_try: no whole frame yet */

int emb_report_take(emb_link *lk, uint8_t *out);
int emb_report_peek(const emb_link *lk, uint32_t *at, uint8_t *out);
int emb_stream_fill(emb_link *lk, int fd);
int emb_stream_try(emb_link *lk, int slave, uint8_t *rsp, int *got);
long emb_stream_take_idle(emb_link *lk);
int64_t emb_settle_until(int64_t start_ns, int64_t last_ns, int total_ms, int quiet_ms,
                         int limit_ms);

#endif
