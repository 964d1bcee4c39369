/* edgemodbus: one turn of a loop thread in one C call (see emb_loop_turn.h).
 *
 * A link that comes back with an event is held (emb_loop_link.held) until Python has
 * run it again (src/edgemodbus/_ffi/loop.py LoopLink.run clears it), so a slot both
 * ready and expired in one wait runs once after an event and its event is listed once.
 * Nothing here allocates: the caller owns every array (ready: max_ready entries,
 * expired: lp->cap, out_slot and out_ev: max_ready + lp->cap). */
#include "emb_loop_turn.h"

#include "emb_util.h" /* emb_now_ns */

/* The link waits, but Python has counters or traced frames to take (as the line worker
 * takes them after each run: src/edgemodbus/line/link.py ContextLink.collect). */
static int emb_lt_collect_due(const emb_loop_link *k)
{
    const emb_link *lk = k->e->lk;

    return (lk->trace && lk->trace->n > 0) || lk->heartbeats || lk->dropped ||
           lk->reports_lost || lk->discarded;
}

/* List slot's event once (a slot without a link can be both ready and expired: then
 * it is due).  The new count. */
static int emb_lt_put(uint32_t *out_slot, int *out_ev, int n, uint32_t slot, int ev)
{
    int i;

    for (i = 0; i < n; i++) {
        if (out_slot[i] == slot) {
            if (ev == EMB_LT_DUE)
                out_ev[i] = ev;
            return n;
        }
    }
    out_slot[n] = slot;
    out_ev[n] = ev;
    return n + 1;
}

/* Run the link of one ready or expired slot; list it when Python must see it. */
static int emb_lt_step(emb_loop *lp, emb_loop_link **links, uint32_t slot, int due,
                       uint32_t *out_slot, int *out_ev, int n)
{
    emb_loop_link *k;
    int ev;

    if (slot >= lp->cap)
        return n;
    k = links[slot];
    if (k == NULL)
        return emb_lt_put(out_slot, out_ev, n, slot, due ? EMB_LT_DUE : EMB_LT_READY);
    if (k->held)
        return n;
    ev = emb_loop_link_run(lp, k);
    if (ev == 0 && emb_lt_collect_due(k))
        ev = EMB_LT_COLLECT;
    if (ev == 0)
        return n;
    k->held = 1;
    out_slot[n] = slot;
    out_ev[n] = ev;
    return n + 1;
}

/* Wait (emb_loop_wait), run the ready links, then the expired ones (earliest first),
 * and again, until a link came back with an event, the loop was woken (*woken) or
 * until_ns passed.  The events listed (out_slot[i], out_ev[i]), or -1 with errno. */
int emb_loop_turn(emb_loop *lp, emb_loop_link **links, int64_t until_ns, uint32_t *ready,
                  uint32_t *ready_events, int max_ready, uint32_t *expired,
                  uint32_t *out_slot, int *out_ev, int *woken)
{
    int n_ready, n_expired, n_out, i;

    for (;;) {
        n_ready = emb_loop_wait(lp, until_ns, ready, ready_events, max_ready, expired,
                                (int)lp->cap, &n_expired, woken);
        if (n_ready == -1)
            return -1;
        n_out = 0;
        for (i = 0; i < n_ready; i++)
            n_out = emb_lt_step(lp, links, ready[i], 0, out_slot, out_ev, n_out);
        for (i = 0; i < n_expired; i++)
            n_out = emb_lt_step(lp, links, expired[i], 1, out_slot, out_ev, n_out);
        if (n_out || *woken || emb_now_ns() >= until_ns)
            return n_out;
    }
}
