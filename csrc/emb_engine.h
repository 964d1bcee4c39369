/* edgemodbus: the line engine, a line's poll loop in C.
 *
 * A line worker hands its devices' read plans to the engine and calls emb_engine_run()
 * with the GIL released.  The engine runs whole passes (cycles) of every device on the
 * line: it picks the device due first, reads and decodes each block due in its pass
 * (emb_read + emb_decode: request interval, silence and checks as one transaction), keeps
 * every block's due time, runs the fault policy beside the read (csrc/emb_fault.c:
 * retries, settle and drain, a block's failure and its reason, the end of a slave's cycle
 * on a timeout, offline and backoff probing), and comes back to Python only when there
 * is something for Python to do: passes with news (changed items, items to invalidate,
 * a status to change), an exception 02 on a block Python can split, a lost link, a job
 * queued by another thread, input on an idle link that takes unsolicited frames, or the
 * caller's deadline.  The structures are owned by the Python side (cffi); the engine
 * allocates nothing. */
#ifndef EMB_ENGINE_H
#define EMB_ENGINE_H

#include "emb_edev.h"
#include "emb_fault.h"

int emb_engine_run(emb_engine *e, int64_t until_ns);
emb_device *emb_engine_pick(const emb_engine *e, int *which);
int emb_engine_reports(emb_engine *e, int which);
uint32_t emb_dev_begin_pass(emb_device *d, int64_t now_ns);
int emb_dev_end_pass(emb_device *d, int64_t now_ns, const int64_t *bounds_ns,
                     uint32_t n_bounds);
void emb_dev_all_due(emb_device *d, int64_t at_ns);
int emb_dev_split(emb_device *d, emb_eblock *blocks, uint32_t *pass_list, uint32_t at,
                  uint32_t k);

#endif
