/* edgemodbus: the gateway's Modbus TCP server (serve and forward modes, see
 * src/edgemodbus/serve/).
 *
 * One thread runs emb_sv_run with the GIL released: poll() over the listening socket, the
 * masters' connections and an eventfd; it frames requests (MBAP, Modbus Messaging on
 * TCP/IP Implementation Guide 1.0b, 3.1.3) and answers reads of cached units from their
 * register image with libmodbus's modbus_reply / modbus_reply_exception, without Python.
 * Requests that need Python (writes to cached units, anything to a forward unit) are
 * handed back one at a time (EMB_SV_EV_REQUEST); Python answers later, from any thread,
 * with emb_sv_post.  The images are updated by Python in batches (emb_sv_update) under
 * the server's mutex. */
#ifndef EMB_SERVE_H
#define EMB_SERVE_H

#include <pthread.h>
#include <stdint.h>
#include <modbus.h>

#define EMB_SV_ADU 260   /* MODBUS_TCP_MAX_ADU_LENGTH */
#define EMB_SV_UNITS 256 /* unit ids 0..255 */
#define EMB_SV_NETS 32   /* networks of one allow-list (the server's, a unit's) */

/* emb_sv_run's events */
#define EMB_SV_EV_DEADLINE 0 /* until_ns reached */
#define EMB_SV_EV_REQUEST 1  /* a request for Python: ev_conn, ev_gen, ev_adu, ev_len */
#define EMB_SV_EV_STOP 2     /* emb_sv_stop was called */
#define EMB_SV_EV_ERROR 3    /* poll() failed: errno */

/* a unit's mode */
#define EMB_SV_NONE 0    /* not served: exception 0A (gateway path unavailable) */
#define EMB_SV_CACHED 1  /* reads from the image, writes to Python */
#define EMB_SV_FORWARD 2 /* every request to Python */

/* the state of one address of an image (emb_sv_unit.state) */
#define EMB_SV_UNMAPPED 0 /* no item: exception 02 */
#define EMB_SV_VALID 1    /* an item's value */
#define EMB_SV_INVALID 2  /* an item Invalid or Unknown: exception 0B */
#define EMB_SV_WRITABLE 4 /* flag: writes to it go to Python */

/* emb_sv_post's kinds */
#define EMB_SV_POST_PDU 0       /* a reply PDU (forward mode) sent with an MBAP header */
#define EMB_SV_POST_EXCEPTION 1 /* data[0] is an exception code (modbus_reply_exception) */
#define EMB_SV_POST_WRITTEN 2   /* the write was confirmed: modbus_reply applies it to the
                                 * image and answers the echo */

/* emb_sv_unit.stale's indexes: why a cached read was answered 0B */
#define EMB_SV_STALE_AGE 0
#define EMB_SV_STALE_INVALID 1

/* the areas, in libmodbus's mapping order */
#define EMB_SV_COILS 0
#define EMB_SV_DISCRETE 1
#define EMB_SV_HOLDING 2
#define EMB_SV_INPUT 3

typedef struct {
    modbus_mapping_t *map; /* values, over each area's span (libmodbus's mapping) */
    uint8_t *state[4];     /* per address of each area's span: EMB_SV_* */
    int64_t fresh_until_ns; /* reads after it (emb_now_ns) get 0B */
    int mode;
    uint64_t stale[2];     /* reads answered 0B: [EMB_SV_STALE_AGE] older than its max
                            * age, [EMB_SV_STALE_INVALID] an item Invalid or not read yet */
} emb_sv_unit;

/* an IPv4 network of an allow-list, host byte order: a source is in it when
 * (source & mask) == addr */
typedef struct {
    uint32_t addr;
    uint32_t mask;
} emb_sv_net;

typedef struct {
    uint32_t n;      /* 0: every source */
    emb_sv_net nets[EMB_SV_NETS];
} emb_sv_allow_list;

typedef struct {
    int fd;          /* -1: the slot is free */
    uint32_t src;    /* the master's IPv4 address, host byte order */
    uint32_t gen;    /* bumped per connection the slot holds: posts for another are dropped */
    int busy;        /* a request is with Python: nothing more is read meanwhile */
    int ready;       /* Python posted the answer (under the mutex) */
    int out_kind;
    int out_len;
    int64_t last_ns; /* the last request or reply: the idle timeout runs from there */
    uint32_t have;   /* bytes in buf */
    uint8_t buf[EMB_SV_ADU];
    uint8_t out[EMB_SV_ADU];
} emb_sv_conn;

typedef struct {
    uint64_t accepted;
    uint64_t refused;     /* over the connection cap: closed at once */
    uint64_t closed_idle;
    uint64_t closed_bad;  /* bad MBAP header (protocol id, length), a failed send */
    uint64_t closed_peer;
    uint64_t requests;
    uint64_t cached_replies;   /* reads answered from the image */
    uint64_t to_python;
    uint64_t exceptions[12];   /* sent, by code (0..11) */
    uint64_t accept_errors;    /* accept4 failed for want of fds or memory (EMFILE, ENFILE,
                                * ENOBUFS, ENOMEM): accepting paused, see emb_sv_accept */
    int accept_errno;          /* the last of those failures' errno */
    uint64_t refused_source;   /* connections from a source outside the server's
                                * allow-list: reset at once */
    uint64_t refused_unit;     /* requests from a source outside their unit's allow-list:
                                * exception 0A, as for a unit not served */
} emb_sv_counters;

typedef struct {
    modbus_t *ctx;     /* a TCP context that only frames replies (socket set per reply) */
    int listen_fd;
    int wake_fd;       /* eventfd: a post, or stop */
    int stop;
    uint32_t max_conns;
    emb_sv_conn *conns;
    void *pfds;        /* struct pollfd[max_conns + 2] */
    uint32_t *pidx;    /* pfds index -> conn slot */
    int64_t idle_ns;   /* 0: no idle timeout */
    int64_t accept_pause_ns; /* the last pause after an accept error (0: none) */
    int64_t accept_at_ns;    /* the listening socket is not polled before then */
    pthread_mutex_t lock; /* the units and the posts */
    emb_sv_unit units[EMB_SV_UNITS];
    emb_sv_allow_list allow;              /* the server's (under the lock) */
    emb_sv_allow_list unit_allow[EMB_SV_UNITS]; /* each unit's (under the lock) */
    emb_sv_counters c;
    /* the event handed to Python */
    int ev_conn;
    uint32_t ev_gen;
    int ev_len;
    uint32_t ev_src;   /* the master's IPv4 address (host byte order; 0: not IPv4) */
    uint8_t ev_adu[EMB_SV_ADU];
} emb_server;

/* one run of an image update: count addresses of an area from start get the values
 * values[first..first+count) (ignored for state EMB_SV_INVALID) and the state */
typedef struct {
    uint8_t unit;
    uint8_t area;
    uint8_t state;
    uint16_t start;
    uint16_t count;
    uint32_t first;
} emb_sv_run_op;

emb_server *emb_sv_new(const char *ip, int port, int backlog, uint32_t max_conns,
                       int64_t idle_ns);
int emb_sv_port(const emb_server *s);
int emb_sv_allow(emb_server *s, int unit, const uint32_t *nets, uint32_t n);
void emb_sv_free(emb_server *s);
int emb_sv_unit_set(emb_server *s, int unit, int mode, const int *spans);
void emb_sv_unit_fresh(emb_server *s, int unit, int64_t until_ns);
/* the unit's reads answered 0B since it was set, by reason (EMB_SV_STALE_*): out[2] */
void emb_sv_unit_stale(emb_server *s, int unit, uint64_t *out);
void emb_sv_update(emb_server *s, const emb_sv_run_op *ops, uint32_t n_ops,
                   const uint16_t *values);
/* data: len bytes (NULL when len is 0) */
int emb_sv_post(emb_server *s, int conn, uint32_t gen, int kind, const uint8_t *data,
                int len);
void emb_sv_stop(emb_server *s);
int emb_sv_run(emb_server *s, int64_t until_ns);
int emb_sv_open_connections(emb_server *s);

#endif
