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
#define EMB_EV_SPLIT ...
#define EMB_FAIL_RSP ...
#define EMB_EXC_SLOTS ...
#define EMB_FAIL_NONE ...
#define EMB_FAIL_OWN ...
#define EMB_FAIL_SILENT ...
#define EMB_ST_BACK ...
#define EMB_ST_OFFLINE ...
#define EMB_ST_AGAIN ...

typedef struct emb_exc_counts {
    uint64_t n[...];
    uint8_t code[...];
    uint64_t other;
} emb_exc_counts;

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
    uint8_t splittable;
    uint8_t fail_kind;
    uint8_t fail_new;
    uint8_t fail_known;
    uint8_t fail_function;
    uint16_t fail_start;
    uint16_t fail_count;
    int fail_errno;
    uint16_t fail_rsp_len;
    uint8_t fail_header;
    uint8_t fail_rsp[...];
    uint8_t rep_ok;
    uint8_t rep_pending;
    uint32_t rep_n;
    const uint32_t *rep_span;
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
    uint64_t retries;
    uint64_t timeouts;
    uint64_t crc_errors;
    uint64_t protocol_errors;
    uint64_t failed_cycles;
    uint64_t skipped_blocks;
    emb_exc_counts exceptions;
    uint64_t reports;
} emb_dev_counters;

typedef struct emb_line_counters {
    uint64_t requests;
    uint64_t responses;
    int64_t rtt_ns;
    int64_t discarded;
    int64_t heartbeats;
    uint64_t timeouts;
    uint64_t crc_errors;
    uint64_t protocol_errors;
    emb_exc_counts exceptions;
    uint64_t reports;
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
    int retries;
    uint32_t offline_after;
    int64_t max_backoff_ns;
    uint32_t failed_cycles;
    uint8_t offline;
    uint8_t running;
    uint8_t status_ev;
    uint8_t timed_out;
    uint8_t answered;
    uint8_t fail_news;
    uint8_t ended;
    int64_t backoff_ns;
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
    uint32_t *rep_list;
    uint32_t n_rep;
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
    uint32_t *ended_list;
    uint32_t n_ended;
    int64_t idle_ns;
    int64_t latest_ns;
    emb_line_counters *lc;
    int settle_ms;
    int settle_limit_ms;
    int quiet_ms;
    int drain_limit_ms;
    uint16_t *rep_regs;
    uint8_t *rep_bits;
} emb_engine;

int emb_engine_run(emb_engine *e, int64_t until_ns);
uint32_t emb_dev_begin_pass(emb_device *d, int64_t now_ns);
int emb_dev_end_pass(emb_device *d, int64_t now_ns, const int64_t *bounds_ns,
                     uint32_t n_bounds);
void emb_dev_all_due(emb_device *d, int64_t at_ns);
void emb_dev_due_at(emb_device *d, int64_t at_ns);
int emb_dev_split(emb_device *d, emb_eblock *blocks, uint32_t *pass_list, uint32_t at,
                  uint32_t k);
int emb_reports_apply(emb_engine *e, int cur_dev, const emb_eblock *cur);
long emb_decode_range(emb_plan *p, const uint32_t *span, const void *data, uint32_t count,
                      uint32_t lo, uint32_t hi, uint32_t *found);

/* csrc/emb_fault.h, for cffi (its tests drive the policy without I/O). */
#define EMB_K_TIMEOUT ...
#define EMB_K_CRC ...
#define EMB_K_PROTOCOL ...
#define EMB_K_EXCEPTION ...
#define EMB_K_LINK ...
int emb_fault_kind(int err, int *code);
void emb_exc_count(emb_exc_counts *x, int code);
void emb_fault_end_pass(emb_device *d, int64_t now_ns);
