/* edgemodbus: the core of the loop engine (issue #27): one thread serves many links.
 *
 * A loop thread owns one epoll set (the sockets of its links, each registered with the
 * link's slot number, and one eventfd other threads write to when they queue a job for
 * a link of this thread) and one timer structure, a binary min-heap of the links' next
 * deadlines (due time, reply timeout, inter-frame silence, settle, backoff: one per
 * link, the earliest the link's state machine waits for).  emb_loop_wait() sleeps until
 * a socket is ready, a deadline passes, the eventfd is written or the caller's own
 * deadline, and hands back the ready slots and the expired ones in arrays the caller
 * owns.  Nothing here allocates: the caller (src/edgemodbus/_ffi/loop.py) allocates the
 * heap and the position table for `cap` slots; the structure runs with the GIL
 * released and keeps no globals.  Only the loop's own thread calls anything but
 * emb_loop_wake(). */
#ifndef EMB_LOOP_H
#define EMB_LOOP_H

#include <stdint.h>
#include <sys/epoll.h>

#define EMB_LOOP_WAKE_SLOT 0xFFFFFFFFu /* the eventfd's epoll tag (no link has it) */
#define EMB_LOOP_NO_TIMER INT64_MAX    /* emb_timer_next with no timer set */
/* what emb_loop_wait reports of a ready socket (its epoll events) */
#define EMB_LOOP_IN EPOLLIN
#define EMB_LOOP_OUT EPOLLOUT
#define EMB_LOOP_HUP (EPOLLHUP | EPOLLRDHUP)
#define EMB_LOOP_ERR EPOLLERR

/* One deadline: the link's slot and when. */
typedef struct {
    int64_t due_ns;
    uint32_t slot;
} emb_timer;

typedef struct {
    int epfd;          /* the epoll set, -1: closed */
    int wakefd;        /* the eventfd, -1: closed */
    uint32_t cap;      /* slots 0..cap-1 */
    uint32_t n_timers; /* entries of heap in use */
    emb_timer *heap;   /* cap entries: a min-heap on due_ns (ties: the lower slot) */
    uint32_t *pos;     /* cap entries: a slot's index in heap + 1, 0: no timer */
} emb_loop;

int emb_loop_open(emb_loop *lp);
void emb_loop_close(emb_loop *lp);
int emb_loop_watch(emb_loop *lp, int fd, uint32_t slot, int want_write);
int emb_loop_unwatch(emb_loop *lp, int fd);
int emb_loop_wake(const emb_loop *lp);
int emb_timer_set(emb_loop *lp, uint32_t slot, int64_t due_ns);
int emb_timer_clear(emb_loop *lp, uint32_t slot);
int64_t emb_timer_next(const emb_loop *lp);
int64_t emb_timer_of(const emb_loop *lp, uint32_t slot);
int emb_loop_wait(emb_loop *lp, int64_t until_ns, uint32_t *ready, uint32_t *ready_events,
                  int max_ready, uint32_t *expired, int max_expired, int *n_expired,
                  int *woken);

#endif
