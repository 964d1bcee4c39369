/* edgemodbus: the fault policy of the line engine (see emb_fault.c). */
#ifndef EMB_FAULT_H
#define EMB_FAULT_H

#include "emb_edev.h"

/* What a failed read was (emb_fault_kind). */
#define EMB_K_TIMEOUT 1   /* no reply, or one that stopped short: retried, settled */
#define EMB_K_CRC 2       /* a bad CRC: retried, drained */
#define EMB_K_PROTOCOL 3  /* any other bad reply: drained */
#define EMB_K_EXCEPTION 4 /* an exception response: a whole, valid frame */
#define EMB_K_LINK 5      /* the link failed: the pass stops, Python reconnects */

int emb_fault_kind(int err, int *code);
int emb_fault_read(emb_engine *e, emb_device *d, emb_eblock *b, void *data);
void emb_fault_end_pass(emb_device *d, int64_t now_ns);
void emb_dev_due_at(emb_device *d, int64_t at_ns);

#endif
