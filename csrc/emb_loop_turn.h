/* edgemodbus: one turn of a loop thread in one C call (issue #27): wait on the loop's
 * epoll set and deadlines (csrc/emb_loop.c), run every ready or expired link's state
 * machine (csrc/emb_loop_link.c), and repeat without coming back to the caller until a
 * link has something Python must see, another thread woke the loop, or the caller's
 * deadline.  Python then handles only those links: at most one GIL entry per turn. */
#ifndef EMB_LOOP_TURN_H
#define EMB_LOOP_TURN_H

#include "emb_loop_link.h"

/* What a turn hands back per slot, besides the link events of emb_loop_link_run
 * (EMB_EV_CYCLE, EMB_EV_SPLIT, EMB_EV_REPORTS, EMB_EV_FAILED, and EMB_EV_WAKE: the link is
 * idle and Python flagged jobs for it, emb_loop_link.jobs): */
#define EMB_LT_COLLECT 16 /* the link waits, but its frame trace or stream counters
                           * (heartbeats, dropped frames, lost reports, bytes discarded)
                           * hold something for Python to log or count */
#define EMB_LT_READY 17   /* a slot without a link is ready (a connect under way) */
#define EMB_LT_DUE 18     /* a slot without a link reached its deadline (reconnect delay,
                           * connect timeout) */

int emb_loop_turn(emb_loop *lp, emb_loop_link **links, int64_t until_ns, uint32_t *ready,
                  uint32_t *ready_events, int max_ready, uint32_t *expired,
                  uint32_t *out_slot, int *out_ev, int *woken);

#endif
