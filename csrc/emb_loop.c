/* edgemodbus: the core of the loop engine: epoll set, wake-up eventfd and the links'
 * deadlines as a min-heap (see emb_loop.h). */
#include "emb_loop.h"

#include <errno.h>
#include <stdint.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include "emb_util.h" /* emb_now_ns */

#define EMB_LOOP_BATCH 64 /* epoll events taken per wait */

/* The epoll set and the eventfd, the heap empty.  lp->cap, heap and pos are the
 * caller's (pos zeroed).  0, or -1 with errno (nothing left open). */
int emb_loop_open(emb_loop *lp)
{
    struct epoll_event ev;
    int err;

    lp->n_timers = 0;
    lp->epfd = epoll_create1(EPOLL_CLOEXEC);
    if (lp->epfd == -1) {
        lp->wakefd = -1;
        return -1;
    }
    lp->wakefd = eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (lp->wakefd == -1)
        goto fail;
    ev.events = EPOLLIN;
    ev.data.u64 = EMB_LOOP_WAKE_SLOT;
    if (epoll_ctl(lp->epfd, EPOLL_CTL_ADD, lp->wakefd, &ev) == -1)
        goto fail;
    return 0;
fail:
    err = errno;
    emb_loop_close(lp);
    errno = err;
    return -1;
}

/* Close the epoll set and the eventfd (the links' sockets stay the caller's). */
void emb_loop_close(emb_loop *lp)
{
    if (lp->wakefd != -1)
        close(lp->wakefd);
    if (lp->epfd != -1)
        close(lp->epfd);
    lp->wakefd = -1;
    lp->epfd = -1;
}

/* Watch fd for slot: readable (hang-up and error included), and writable too while a
 * request is only partly sent (want_write).  Added, or changed when already watched.
 * 0, or -1 with errno (EINVAL: a slot out of range). */
int emb_loop_watch(emb_loop *lp, int fd, uint32_t slot, int want_write)
{
    struct epoll_event ev;

    if (slot >= lp->cap) {
        errno = EINVAL;
        return -1;
    }
    ev.events = EPOLLIN | EPOLLRDHUP | (want_write ? EPOLLOUT : 0u);
    ev.data.u64 = slot;
    if (epoll_ctl(lp->epfd, EPOLL_CTL_MOD, fd, &ev) == 0)
        return 0;
    if (errno != ENOENT)
        return -1;
    return epoll_ctl(lp->epfd, EPOLL_CTL_ADD, fd, &ev);
}

/* Stop watching fd (before the caller closes it).  0, or -1 with errno. */
int emb_loop_unwatch(emb_loop *lp, int fd)
{
    struct epoll_event ev = {0};

    return epoll_ctl(lp->epfd, EPOLL_CTL_DEL, fd, &ev);
}

/* Wake the loop from any thread (a job was queued).  Writes coalesce: one wake-up for
 * any number of jobs.  0, or -1 with errno. */
int emb_loop_wake(const emb_loop *lp)
{
    uint64_t one = 1;

    if (write(lp->wakefd, &one, sizeof one) == (ssize_t)sizeof one)
        return 0;
    return errno == EAGAIN ? 0 : -1; /* the counter is full: a wake-up is pending */
}

static int emb_timer_less(const emb_timer *a, const emb_timer *b)
{
    return a->due_ns < b->due_ns || (a->due_ns == b->due_ns && a->slot < b->slot);
}

static void emb_timer_place(emb_loop *lp, uint32_t i, emb_timer t)
{
    lp->heap[i] = t;
    lp->pos[t.slot] = i + 1;
}

/* Move the entry at i up, then down, to where the heap order puts it. */
static void emb_timer_fix(emb_loop *lp, uint32_t i)
{
    emb_timer t = lp->heap[i];
    uint32_t parent, child;

    while (i > 0) {
        parent = (i - 1) / 2;
        if (!emb_timer_less(&t, &lp->heap[parent]))
            break;
        emb_timer_place(lp, i, lp->heap[parent]);
        i = parent;
    }
    for (;;) {
        child = 2 * i + 1;
        if (child >= lp->n_timers)
            break;
        if (child + 1 < lp->n_timers && emb_timer_less(&lp->heap[child + 1], &lp->heap[child]))
            child++;
        if (!emb_timer_less(&lp->heap[child], &t))
            break;
        emb_timer_place(lp, i, lp->heap[child]);
        i = child;
    }
    emb_timer_place(lp, i, t);
}

/* Set (or move) slot's deadline to due_ns.  0, or -1 with EINVAL (slot out of range). */
int emb_timer_set(emb_loop *lp, uint32_t slot, int64_t due_ns)
{
    uint32_t i;

    if (slot >= lp->cap) {
        errno = EINVAL;
        return -1;
    }
    if (lp->pos[slot]) {
        i = lp->pos[slot] - 1;
    } else {
        i = lp->n_timers++;
    }
    lp->heap[i].due_ns = due_ns;
    lp->heap[i].slot = slot;
    lp->pos[slot] = i + 1;
    emb_timer_fix(lp, i);
    return 0;
}

/* Remove slot's deadline, if it has one.  0, or -1 with EINVAL (slot out of range). */
int emb_timer_clear(emb_loop *lp, uint32_t slot)
{
    uint32_t i;

    if (slot >= lp->cap) {
        errno = EINVAL;
        return -1;
    }
    if (!lp->pos[slot])
        return 0;
    i = lp->pos[slot] - 1;
    lp->pos[slot] = 0;
    lp->n_timers--;
    if (i < lp->n_timers) {
        emb_timer_place(lp, i, lp->heap[lp->n_timers]);
        emb_timer_fix(lp, i);
    }
    return 0;
}

/* The earliest deadline, EMB_LOOP_NO_TIMER with none. */
int64_t emb_timer_next(const emb_loop *lp)
{
    return lp->n_timers ? lp->heap[0].due_ns : EMB_LOOP_NO_TIMER;
}

/* Slot's deadline, EMB_LOOP_NO_TIMER with none (or a slot out of range). */
int64_t emb_timer_of(const emb_loop *lp, uint32_t slot)
{
    if (slot >= lp->cap || !lp->pos[slot])
        return EMB_LOOP_NO_TIMER;
    return lp->heap[lp->pos[slot] - 1].due_ns;
}

/* Sleep until a watched socket is ready, the earliest deadline or until_ns passes, or
 * the loop is woken; then hand back the ready slots (their epoll events beside them, at
 * most max_ready) and pop the deadlines that passed (at most max_expired, earliest
 * first, into expired; *n_expired).  *woken: the eventfd was written (its count is
 * reset).  A deadline popped is gone: the state machine sets the next.  The ready
 * slots, or -1 with errno (EINTR is a wait with nothing, not an error). */
int emb_loop_wait(emb_loop *lp, int64_t until_ns, uint32_t *ready, uint32_t *ready_events,
                  int max_ready, uint32_t *expired, int max_expired, int *n_expired,
                  int *woken)
{
    struct epoll_event evs[EMB_LOOP_BATCH];
    int64_t now = emb_now_ns(), stop = emb_timer_next(lp), wait_ms;
    uint64_t count;
    int n, i, got = 0;

    *n_expired = 0;
    *woken = 0;
    if (until_ns < stop)
        stop = until_ns;
    if (stop <= now)
        wait_ms = 0;
    else if (stop - now > (int64_t)3600 * 1000000000)
        wait_ms = 3600 * 1000; /* the caller's deadline comes round again */
    else
        wait_ms = (stop - now + 999999) / 1000000; /* rounded up: never wake early */
    if (max_ready > EMB_LOOP_BATCH - 1)
        max_ready = EMB_LOOP_BATCH - 1; /* one more event: the eventfd's */
    if (max_ready < 0)
        max_ready = 0;
    /* level-triggered: a ready socket left over now is handed back by the next wait */
    n = epoll_wait(lp->epfd, evs, max_ready + 1, (int)wait_ms);
    if (n == -1 && errno != EINTR)
        return -1;
    for (i = 0; i < n; i++) {
        if (evs[i].data.u64 == EMB_LOOP_WAKE_SLOT) {
            *woken = 1;
            if (read(lp->wakefd, &count, sizeof count) == -1 && errno != EAGAIN)
                return -1;
        } else if (got < max_ready) {
            ready[got] = (uint32_t)evs[i].data.u64;
            ready_events[got] = evs[i].events;
            got++;
        }
    }
    now = emb_now_ns();
    while (lp->n_timers && lp->heap[0].due_ns <= now && *n_expired < max_expired) {
        expired[(*n_expired)++] = lp->heap[0].slot;
        emb_timer_clear(lp, lp->heap[0].slot);
    }
    return got;
}
