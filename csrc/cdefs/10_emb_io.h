/* csrc/emb_io.h (with csrc/emb_link.h, csrc/emb_stream.h, csrc/emb_util.h), for cffi.
 * All return -1 with errno set on failure. */
#define EMB_MAX_ADU ...
#define EMB_MAX_RTU ...
#define EMB_MBAP ...
typedef struct {
    ...;
} emb_stream_buf;

typedef struct {
    uint32_t used;
    uint32_t n;
    long lost;
    ...;
} emb_trace;

typedef struct {
    int mbap;
    int echo;
    unsigned tid;
    long discarded;
    int rsp_len;
    uint32_t char_ns;
    long syscalls;
    int wrapped;
    uint32_t hb_len;
    uint8_t hb[64];
    long heartbeats;
    long dropped;
    long reports_lost;
    uint8_t last_drop[32];
    int last_drop_len;
    uint32_t n_reports;
    uint32_t n_before;
    emb_stream_buf *sb;
    uint8_t *ring;
    emb_trace *trace;
    ...;
} emb_link;

#define EMB_HB_MAX ...
#define EMB_REPORT_MAX ...
#define EMB_RING_SIZE ...
#define EMB_TRACE_SIZE ...
#define EMB_TRACE_TX ...
#define EMB_TRACE_RX ...

#define EMB_EBASE ...
#define EMB_EEXCEPTION ...
#define EMB_EPARTIAL ...
#define EMB_EECHO ...
#define EMB_EECHOSEEN ...
#define EMB_ESLAVE ...
#define EMB_EFUNCTION ...
#define EMB_EOTHEREXC ...
#define EMB_ECOUNT ...
#define EMB_ETID ...
#define EMB_EPROTOID ...
#define EMB_EMBAPLEN ...
#define EMB_EWECHO ...
#define EMB_ELENGTH ...

int emb_read(modbus_t *ctx, emb_link *lk, int slave, int function, int addr, int nb,
             void *dest, uint8_t *rsp);
int emb_transact(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                 uint8_t *rsp);
int emb_send(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len);
int emb_request(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                int timeout_ms, uint8_t *rsp);
int emb_write_pdu(int function, int addr, int nb, const uint16_t *values, uint8_t *pdu);
int emb_write(modbus_t *ctx, emb_link *lk, int slave, int function, int addr, int nb,
              const uint16_t *values, int timeout_ms, uint8_t *req, uint8_t *rsp);
long emb_discard_input(int fd, int total_ms, int quiet_ms, int limit_ms);
long emb_link_discard(modbus_t *ctx, emb_link *lk, int total_ms, int quiet_ms, int limit_ms);
long emb_pump(modbus_t *ctx, emb_link *lk);
long emb_feed(emb_link *lk, const uint8_t *data, int n);
int emb_report_take(emb_link *lk, uint8_t *out);
int emb_trace_take(emb_trace *t, uint8_t *out, int *direction, int64_t *t_ns);
int64_t emb_now_ns(void);
uint16_t emb_crc16(const uint8_t *p, int n);

/* csrc/emb_check.h: the one reply check */
int emb_check_reply(const uint8_t *req, int req_len, const uint8_t *rsp, int rsp_len,
                    int *exc);
int emb_check_adu(int mbap, long tid, int slave, const uint8_t *pdu, int pdu_len,
                  const uint8_t *adu, int adu_len, int *exc);
