/* edgemodbus: the DTU stream link kinds of csrc/emb_stream.c (heartbeats, wrapped report
 * frames) and their report ring. */
#ifndef EMB_STREAM_H
#define EMB_STREAM_H

#include "emb_backend.h"

extern const emb_backend emb_stream_backend;
extern const emb_backend emb_wrapped_backend;

int emb_report_take(emb_link *lk, uint8_t *out);

#endif
