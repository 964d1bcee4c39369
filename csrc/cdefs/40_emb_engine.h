/* csrc/emb_engine.h, for cffi. */
#define EMB_HIST_MAX ...
#define EMB_EV_DEADLINE ...
#define EMB_EV_CYCLE ...
#define EMB_EV_FAILED ...
#define EMB_EV_WAKE ...
#define EMB_EV_INPUT ...
#define EMB_EV_ERROR ...
#define EMB_EV_TRACE ...
#define EMB_EV_REPORTS ...

typedef struct emb_eblock {
    emb_plan *plan;
    void *data;
    int64_t period_ns;
    int64_t due_ns;
    int64_t read_ns;
    long reported;
    uint16_t start;
    uint16_t count;
    uint8_t function;
    uint8_t keep;
} emb_eblock;

typedef struct emb_dev_counters {
    uint64_t requests;
    uint64_t responses;
    uint64_t cycles;
    uint64_t overruns;
    int64_t last_cycle_ns;
    int64_t total_cycle_ns;
    int64_t max_cycle_ns;
    uint64_t hist[...];
} emb_dev_counters;

typedef struct emb_line_counters {
    uint64_t requests;
    uint64_t responses;
    int64_t rtt_ns;
    int64_t discarded;
    int64_t heartbeats;
} emb_line_counters;

typedef struct emb_device {
    emb_eblock *blocks;
    uint32_t *pass_list;
    uint32_t n_blocks;
    uint32_t n_pass;
    uint32_t index;
    uint32_t taken;
    int slave;
    int timeout_ms;
    int mode;
    uint8_t active;
    uint8_t notify;
    uint8_t in_pass;
    uint8_t news;
    int64_t cycle_ns;
    int64_t notify_ns;
    int64_t due_ns;
    int64_t pass_start_ns;
    uint64_t passes;
    emb_dev_counters c;
} emb_device;

typedef struct emb_engine {
    modbus_t *ctx;
    emb_link *lk;
    uint8_t *rsp;
    uint16_t *regs;
    uint8_t *bits;
    emb_device **devices;
    uint32_t n_devices;
    int wake_fd;
    int watch_fd;
    const int *wake;
    int timeout_ms;
    int64_t pace_ns;
    int64_t ready_ns;
    uint8_t owed;
    const int64_t *bounds_ns;
    uint32_t n_bounds;
    int event_device;
    int event_errno;
    emb_line_counters *lc;
} emb_engine;

int emb_engine_run(emb_engine *e, int64_t until_ns);
uint32_t emb_dev_begin_pass(emb_device *d, int64_t now_ns);
int emb_dev_end_pass(emb_device *d, int64_t now_ns, const int64_t *bounds_ns,
                     uint32_t n_bounds);
void emb_dev_all_due(emb_device *d, int64_t at_ns);
