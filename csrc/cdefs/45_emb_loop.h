/* csrc/emb_loop.h, for cffi. */
#define EMB_LOOP_WAKE_SLOT ...
#define EMB_LOOP_NO_TIMER ...
#define EMB_LOOP_IN ...
#define EMB_LOOP_OUT ...
#define EMB_LOOP_HUP ...
#define EMB_LOOP_ERR ...

typedef struct {
    int64_t due_ns;
    uint32_t slot;
} emb_timer;

typedef struct {
    int epfd;
    int wakefd;
    uint32_t cap;
    uint32_t n_timers;
    emb_timer *heap;
    uint32_t *pos;
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

/* csrc/emb_stream.h: the non-blocking framer of plain RTU streams, which the loop
 * engine receives with */
#define EMB_STREAM_MORE ...
int emb_stream_fill(emb_link *lk, int fd);
int emb_stream_try(emb_link *lk, int slave, uint8_t *rsp, int *got);
long emb_stream_take_idle(emb_link *lk);
int64_t emb_settle_until(int64_t start_ns, int64_t last_ns, int total_ms, int quiet_ms,
                         int limit_ms);

/* csrc/emb_loop_link.h: one link of the loop engine */
#define EMB_LS_IDLE ...
#define EMB_LS_AWAIT ...
#define EMB_LS_SETTLE ...
#define EMB_LS_FAILED ...
#define EMB_LS_SEND ...
#define EMB_LS_NEXT ...
typedef struct {
    emb_engine *e;
    int fd;
    uint32_t slot;
    int state;
    int jobs;
    int owed;
    int held;
    int which;
    int byte_ms;
    int echo_left;
    int want_out;
    ...;
} emb_loop_link;
int emb_loop_link_run(emb_loop *lp, emb_loop_link *k);

/* csrc/emb_loop_turn.h: one turn of a loop thread in one C call */
#define EMB_LT_COLLECT ...
#define EMB_LT_READY ...
#define EMB_LT_DUE ...
int emb_loop_turn(emb_loop *lp, emb_loop_link **links, int64_t until_ns, uint32_t *ready,
                  uint32_t *ready_events, int max_ready, uint32_t *expired,
                  uint32_t *out_slot, int *out_ev, int *woken);
