/* csrc/emb_serve.h, for cffi. */
#define EMB_SV_ADU ...
#define EMB_SV_UNITS ...
#define EMB_SV_NETS ...
#define EMB_SV_EV_DEADLINE ...
#define EMB_SV_EV_REQUEST ...
#define EMB_SV_EV_STOP ...
#define EMB_SV_EV_ERROR ...
#define EMB_SV_NONE ...
#define EMB_SV_CACHED ...
#define EMB_SV_FORWARD ...
#define EMB_SV_UNMAPPED ...
#define EMB_SV_VALID ...
#define EMB_SV_INVALID ...
#define EMB_SV_WRITABLE ...
#define EMB_SV_POST_PDU ...
#define EMB_SV_POST_EXCEPTION ...
#define EMB_SV_POST_WRITTEN ...
#define EMB_SV_STALE_AGE ...
#define EMB_SV_STALE_INVALID ...

typedef struct {
    uint64_t accepted;
    uint64_t refused;
    uint64_t closed_idle;
    uint64_t closed_bad;
    uint64_t closed_peer;
    uint64_t requests;
    uint64_t cached_replies;
    uint64_t to_python;
    uint64_t exceptions[12];
    uint64_t accept_errors;
    int accept_errno;
    uint64_t refused_source;
    uint64_t refused_unit;
} emb_sv_counters;

typedef struct {
    emb_sv_counters c;
    int ev_conn;
    uint32_t ev_gen;
    int ev_len;
    uint32_t ev_src;
    uint8_t ev_adu[260];
    ...;
} emb_server;

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
void emb_sv_unit_stale(emb_server *s, int unit, uint64_t *out);
void emb_sv_update(emb_server *s, const emb_sv_run_op *ops, uint32_t n_ops,
                   const uint16_t *values);
int emb_sv_post(emb_server *s, int conn, uint32_t gen, int kind, const uint8_t *data,
                int len);
void emb_sv_stop(emb_server *s);
int emb_sv_run(emb_server *s, int64_t until_ns);
int emb_sv_open_connections(emb_server *s);
