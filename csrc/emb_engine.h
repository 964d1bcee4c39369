/* edgemodbus: the line engine, a line's poll loop in C.
 *
 * A line worker hands its devices' read plans to the engine and calls emb_engine_run()
 * with the GIL released.  The engine runs whole passes (cycles) of every device on the
 * line: it picks the device due first, reads and decodes each block due in its pass
 * (emb_read + emb_decode: request interval, silence and checks as one transaction), keeps
 * every block's due time, and comes back to Python only when there is something for
 * Python to do: a pass with news (changed items, or pieces of large items to assemble),
 * a read that failed (Python runs the fault policy: retries, settle, bisection, offline),
 * a job queued by another thread, input on an idle link that takes unsolicited frames,
 * or the caller's deadline.  The structures are owned by the Python side (cffi); the
 * engine allocates nothing. */
#ifndef EMB_ENGINE_H
#define EMB_ENGINE_H

#include <stdint.h>

#include "emb_codec.h"
#include "emb_io.h" /* emb_now_ns too (csrc/emb_util.h) */

#define EMB_HIST_MAX 16 /* cycle-time histogram buckets, the +Inf one included */
#define EMB_JOIN_NS 5000000LL /* a block due this soon joins the pass that begins now */
#define EMB_NEVER INT64_MAX

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
} emb_dev_counters;

/* A line's request counters (stats.py LineStats), kept by the engine; Python reads them
 * and never writes them while an engine runs. */
typedef struct emb_line_counters {
    uint64_t requests;
    uint64_t responses;
    int64_t rtt_ns;       /* round-trip times, summed */
    int64_t discarded;    /* bytes thrown away (emb_link.discarded, moved here) */
    int64_t heartbeats;   /* DTU heartbeats skipped (emb_link.heartbeats, moved here) */
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
} emb_device;

/* What emb_engine_run() came back for. */
#define EMB_EV_DEADLINE 0 /* the caller's deadline */
#define EMB_EV_CYCLE 1    /* device event_device ended a pass Python must see */
#define EMB_EV_FAILED 2   /* a read of device event_device failed: event_errno */
#define EMB_EV_WAKE 3     /* a job was queued (event_device: a device left mid-pass);
                           * with owed set, only once a due block was read */
#define EMB_EV_INPUT 4    /* watch_fd is readable while idle (unsolicited frames) */
#define EMB_EV_ERROR 5    /* poll() failed: event_errno */
#define EMB_EV_REPORTS 7  /* a read of device event_device took wrapped reports or dropped
                           * frames besides its reply (a DTU stream): Python applies those
                           * before the reply (emb_link.n_before), the reply, the rest */
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
    emb_line_counters *lc; /* the line's counters, kept across its links */
} emb_engine;

int emb_engine_run(emb_engine *e, int64_t until_ns);
uint32_t emb_dev_begin_pass(emb_device *d, int64_t now_ns);
int emb_dev_end_pass(emb_device *d, int64_t now_ns, const int64_t *bounds_ns,
                     uint32_t n_bounds);
void emb_dev_all_due(emb_device *d, int64_t at_ns);

#endif
