/* edgemodbus: the line engine's data (blocks, devices, counters, the engine), shared by
 * the engine's loop (emb_engine.c) and its fault policy (emb_fault.c); see emb_engine.h. */
#ifndef EMB_EDEV_H
#define EMB_EDEV_H

#include <stdint.h>

#include "emb_codec.h"
#include "emb_io.h" /* emb_now_ns too (csrc/emb_util.h) */

#define EMB_HIST_MAX 16 /* cycle-time histogram buckets, the +Inf one included */
#define EMB_JOIN_NS 5000000LL /* a block due this soon joins the pass that begins now */
#define EMB_HANDOVER_NS 50000000LL /* news waits this long at most for a device due next */
#define EMB_LATEST_NS 1000000000LL /* ... and at most this long on a busy line */
#define EMB_NEVER INT64_MAX
#define EMB_FAIL_RSP 12   /* bytes of a rejected reply kept for its reason */
#define EMB_EXC_SLOTS 8   /* exception codes counted apart (emb_exc_counts) */

#define EMB_FAIL_NONE 0   /* the block's last read was good */
#define EMB_FAIL_OWN 1    /* its own read failed (an exception, CRC or protocol error) */
#define EMB_FAIL_SILENT 2 /* the slave did not answer (this or an earlier block of the pass) */

#define EMB_ST_BACK 1     /* the slave answers (again): Running */
#define EMB_ST_OFFLINE 2  /* the slave went offline */
#define EMB_ST_AGAIN 4    /* with EMB_ST_BACK: it had been offline */

/* Exception responses by code, for the codes that occurred: the first EMB_EXC_SLOTS
 * distinct codes each in a slot (in order of first occurrence), any later code in
 * `other`.  The Modbus Application Protocol 1.1b3, section 7, defines nine codes
 * (01-06, 08, 0A, 0B), and a slave answers few of them, so 80 bytes replace an array of
 * 256 counts (2 kB) per device and per line (docs/scale.md "Memory per DTU"). */
typedef struct emb_exc_counts {
    uint64_t n[EMB_EXC_SLOTS];   /* the count of code[i]; 0: the slot is free */
    uint8_t code[EMB_EXC_SLOTS];
    uint64_t other;              /* codes that found every slot taken */
} emb_exc_counts;

/* One planned read (a block) of a device. */
typedef struct emb_eblock {
    emb_plan *plan;      /* the block's compiled items; NULL: no whole item to decode */
    void *data;          /* the block's own buffer (kept for Python), NULL: the line's */
    int64_t period_ns;   /* the scan rate of its items */
    int64_t due_ns;      /* CLOCK_MONOTONIC of its next read */
    int64_t read_ns;     /* CLOCK_MONOTONIC when its last good read was sent; 0: none */
    long reported;       /* the last decode's count (see emb_decode) */
    uint16_t start;
    uint16_t count;
    uint8_t function;    /* 1..4 */
    uint8_t keep;        /* Python reads this block's data after every good read */
    uint8_t splittable;  /* more than one piece: an exception 02 splits it (EMB_EV_SPLIT) */
    /* its failure (csrc/emb_fault.c), kept until a good read; Python words the reason */
    uint8_t fail_kind;   /* EMB_FAIL_NONE, EMB_FAIL_OWN (fail_errno on this block), or
                          * EMB_FAIL_SILENT (the slave timed out at fail_start..) */
    uint8_t fail_new;    /* a failure Python has not taken yet */
    uint8_t fail_known;  /* Python took it (cleared by a good read, or by Python when
                          * items of the block were set from elsewhere) */
    uint8_t fail_function;  /* the block that failed (itself, or the one that timed out) */
    uint16_t fail_start;
    uint16_t fail_count;
    int fail_errno;
    uint16_t fail_rsp_len;  /* the rejected reply's length (what Python's reason quotes) */
    uint8_t fail_header;    /* its header: 1 (slave id) or 7 (MBAP) */
    uint8_t fail_rsp[EMB_FAIL_RSP]; /* its first bytes */
    /* wrapped reports applied in C (csrc/emb_report.c) */
    uint8_t rep_ok;      /* Python: a report inside the block's range updates exactly the
                          * block's items inside it (no other item lies in the range, no
                          * scale factor table), so the engine may apply it here */
    uint8_t rep_pending; /* a report's decode Python has not taken (rep_n items listed in
                          * the plan's `changed`); nothing else decodes into the plan
                          * until Python took it */
    uint32_t rep_n;
    const uint32_t *rep_span; /* with rep_ok, per item of the plan: its first register (or
                               * bit) in the block and how many it has (its quantity),
                               * which a report must hold whole to update it */
} emb_eblock;

/* A device's counters (stats.py DeviceStats): only the engine's thread writes them. */
typedef struct emb_dev_counters {
    uint64_t requests;
    uint64_t responses;
    uint64_t cycles;
    uint64_t overruns;
    int64_t last_cycle_ns;
    int64_t total_cycle_ns;
    int64_t max_cycle_ns;
    uint64_t hist[EMB_HIST_MAX];
    uint64_t retries;
    uint64_t timeouts;      /* a partial reply too (IncompleteReplyError) */
    uint64_t crc_errors;
    uint64_t protocol_errors;
    uint64_t failed_cycles;
    uint64_t skipped_blocks;
    emb_exc_counts exceptions; /* by exception code */
    uint64_t reports;       /* wrapped reports that held items of the device, applied in C */
} emb_dev_counters;

/* A line's request counters (stats.py LineStats), kept by the engine; Python reads them
 * and never writes them while an engine runs. */
typedef struct emb_line_counters {
    uint64_t requests;
    uint64_t responses;
    int64_t rtt_ns;       /* round-trip times, summed */
    int64_t discarded;    /* bytes thrown away (emb_link.discarded, moved here) */
    int64_t heartbeats;   /* DTU heartbeats skipped (emb_link.heartbeats, moved here) */
    uint64_t timeouts;
    uint64_t crc_errors;
    uint64_t protocol_errors;
    emb_exc_counts exceptions;
    uint64_t reports;     /* wrapped reports taken by the engine (csrc/emb_report.c) */
} emb_line_counters;

/* One polled slave: its blocks, its pass under way and its schedule. */
typedef struct emb_device {
    emb_eblock *blocks;
    uint32_t *pass_list;     /* block indices of the pass under way (room for n_blocks) */
    uint32_t n_blocks;
    uint32_t n_pass;
    uint32_t index;       /* the pass's next block */
    uint32_t taken;       /* the pass's blocks whose results Python has taken */
    int slave;
    int timeout_ms;       /* response timeout */
    /* the fault policy, set once (poll/poller.py); the state is the engine's */
    int retries;          /* a timeout or CRC error is read again this often (not offline) */
    uint32_t offline_after; /* failed cycles in a row that take the slave offline */
    int64_t max_backoff_ns;
    uint32_t failed_cycles; /* in a row */
    uint8_t offline;
    uint8_t running;      /* it answered since Python last said otherwise (link down) */
    uint8_t status_ev;    /* EMB_ST_* bits not yet taken by Python */
    uint8_t timed_out;    /* the pass under way ended on a timeout */
    uint8_t answered;     /* the pass under way had a reply (good or an exception) */
    uint8_t fail_news;    /* a block holds a failure Python has not taken (fail_new) */
    uint8_t ended;        /* a pass ended that Python must see (EMB_EV_CYCLE) */
    int64_t backoff_ns;   /* the probe interval while offline */
    int mode;             /* EMB_MODE_TRACK, or EMB_MODE_ALL (report every item) */
    uint8_t active;       /* polled at all */
    uint8_t notify;       /* Python wants the end of the next pass even without news */
    uint8_t in_pass;
    uint8_t news;         /* the pass under way has reports or kept blocks for Python */
    int64_t cycle_ns;     /* readCycle of a device with no blocks; 0: never due */
    int64_t notify_ns;    /* also notify at the end of the first pass ending after this */
    int64_t due_ns;       /* when its next pass begins (EMB_NEVER: never) */
    int64_t pass_start_ns;
    uint64_t passes;      /* passes begun */
    emb_dev_counters c;
    uint32_t *rep_list;   /* blocks holding a report's decode for Python (rep_pending), in
                           * the order the reports came (room for n_blocks) */
    uint32_t n_rep;
} emb_device;

/* What emb_engine_run() came back for. */
#define EMB_EV_DEADLINE 0 /* the caller's deadline */
#define EMB_EV_CYCLE 1    /* devices ended passes Python must see (their `ended`) */
#define EMB_EV_FAILED 2   /* the link failed on a read of device event_device: event_errno */
#define EMB_EV_WAKE 3     /* a job was queued (event_device: a device left mid-pass);
                           * with owed set, only once a due block was read */
#define EMB_EV_INPUT 4    /* watch_fd is readable while idle (unsolicited frames) */
#define EMB_EV_ERROR 5    /* poll() failed: event_errno */
#define EMB_EV_REPORTS 7  /* wrapped reports the engine could not apply in C (csrc/emb_report.c)
                           * or dropped frames, after a read of device event_device (a DTU
                           * stream): Python applies those before the reply
                           * (emb_link.n_before), the reply, the rest; or the pass's next
                           * block holds a report Python has not taken yet */
#define EMB_EV_SPLIT 8    /* exception 02 on a splittable block of device event_device
                           * (its pass's next block): Python splits it (emb_dev_split) */
#define EMB_EV_TRACE 6    /* the link's frame trace holds frames for Python to log: between
                           * passes once a quarter full or a frame is EMB_TRACE_FLUSH_NS
                           * old, mid-pass (event_device) when half full */

/* One line's engine: its link, its devices, its counters. */
typedef struct emb_engine {
    modbus_t *ctx;
    emb_link *lk;
    uint8_t *rsp;          /* reply ADU buffer, 260 bytes */
    uint16_t *regs;        /* the line's register buffer, 125 registers */
    uint8_t *bits;         /* the line's bit buffer, 2000 bits */
    emb_device **devices;
    uint32_t n_devices;
    int wake_fd;           /* readable while a job waits (-1: none) */
    int watch_fd;          /* watched while idle (-1: none) */
    const int *wake;       /* set by another thread when it queues a job (atomic) */
    int timeout_ms;        /* the response timeout set on ctx (-1: unknown) */
    int64_t pace_ns;       /* silence after a transaction: t3.5 + request interval */
    int64_t ready_ns;      /* no request before this */
    uint8_t owed;          /* a queued job ran since the last read: while a block is due,
                            * the wake flag waits for one read (fair line scheduling) */
    const int64_t *bounds_ns; /* cycle-time histogram upper bounds */
    uint32_t n_bounds;     /* < EMB_HIST_MAX */
    int event_device;
    int event_errno;
    uint32_t *ended_list;  /* indices of the devices whose `ended` is set (room for
                            * n_devices); Python takes them and sets n_ended to 0 */
    uint32_t n_ended;
    int64_t idle_ns;       /* the listed passes go to Python rather than idle this long */
    int64_t latest_ns;     /* ... and by this time at the latest */
    emb_line_counters *lc; /* the line's counters, kept across its links */
    /* cleaning the line after a failed read (line/link.py sets them once) */
    int settle_ms;         /* after a timeout: wait out a late reply (0: no settling) */
    int settle_limit_ms;
    int quiet_ms;          /* silence that ends a stray frame */
    int drain_limit_ms;    /* after a bad frame: its rest */
    /* wrapped reports applied in C (csrc/emb_report.c): a block's registers or bits
     * rebuilt from a report, 125 registers and 2000 bits */
    uint16_t *rep_regs;
    uint8_t *rep_bits;
} emb_engine;

#endif
