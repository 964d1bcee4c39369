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

/* How the line is cleaned after a failure (emb_fault_clean_of). */
#define EMB_CLEAN_NONE 0
#define EMB_CLEAN_SETTLE 1 /* wait out a late reply: settle_ms, quiet_ms, settle_limit_ms */
#define EMB_CLEAN_DRAIN 2  /* drain a bad frame: quiet_ms, quiet_ms, drain_limit_ms */

/* emb_fault_failed: request the block again (not an EMB_EV_*) */
#define EMB_FAULT_RETRY (-2)

int emb_fault_kind(int err, int *code);
void emb_exc_count(emb_exc_counts *x, int code);
/* the policy as pure steps, for an engine that does the I/O itself (csrc/emb_loop.c):
 * sent, the I/O, took; then answered, or count, clean_of + the cleaning + cleaned,
 * failed (the blocking emb_fault_read composes them) */
void emb_fault_sent(emb_engine *e, emb_device *d);
void emb_fault_took(emb_engine *e);
void emb_fault_answered(emb_engine *e, emb_device *d, emb_eblock *b, int rc, void *data,
                        int64_t start_ns, int retried);
int emb_fault_tries(const emb_device *d);
void emb_fault_count(emb_engine *e, emb_device *d, int kind, int code);
int emb_fault_clean_of(const emb_engine *e, int kind);
void emb_fault_cleaned(emb_engine *e, long n);
int emb_fault_failed(emb_engine *e, emb_device *d, emb_eblock *b, int kind, int code,
                     int err, int *tries);
int emb_fault_read(emb_engine *e, emb_device *d, emb_eblock *b, void *data,
                   int64_t until_ns);
void emb_fault_end_pass(emb_device *d, int64_t now_ns);
void emb_dev_due_at(emb_device *d, int64_t at_ns);

#endif
