/* libFuzzer harness for the request path of the gateway's Modbus TCP server in
 * csrc/emb_serve.c: MBAP framing of a connection's byte stream (emb_sv_serve_buffered),
 * the request checks before modbus_reply (emb_sv_request, emb_sv_cached, emb_sv_check),
 * the replies (libmodbus's modbus_reply / modbus_reply_exception) and the answers Python
 * posts (emb_sv_post, emb_sv_flush_posts).  Built by tools/fuzz.py with clang
 * -fsanitize=fuzzer,address,undefined and linked with Debian's libmodbus.
 *
 * emb_serve.c is included here so that its static functions are in reach; nothing of it
 * changes.  The server is made without a listening socket (no network): one connection
 * slot whose fd is one end of a socketpair; the harness writes the master's bytes into
 * the other end, runs the loop's steps in emb_sv_run's order (flush the posts, serve what
 * is buffered, read) and plays Python for the requests handed to it.  Unit 1 is served
 * from an image (spans, states and values from the input, through emb_sv_unit_set and
 * emb_sv_update), unit 2 forwards, every other unit is not served.
 *
 * Contract, checked against a model of the framing (Modbus Messaging on TCP/IP
 * Implementation Guide 1.0b, 3.1.3): every complete request before the first bad MBAP
 * header (protocol id not 0, length outside 2..254) gets exactly one reply, in order,
 * with its transaction id, protocol id 0, a length that matches and its unit id; the
 * connection is closed exactly when a bad header was reached; nothing else is sent.  A
 * unit not served answers 0A; a forward unit what was posted; a read of the image its
 * function with the byte count of its quantity, or an exception 01..04/0B that our
 * checks sent (counted: libmodbus never refuses a request by itself, since its refusal
 * sleeps and flushes the socket); a confirmed write the echo.  The counters (requests,
 * cached replies, handed to Python, exceptions) match.
 *
 * Input layout (missing bytes read as 0):
 *   ctl   bit0 framed: the stream is built from (unit u8, pdu length u8, pdu) with valid
 *         MBAP headers (transaction ids counting up), else the rest is raw bytes;
 *         bit1 the image is fresh (else every read of it is stale: 0B)
 *   chunk u8: the stream is written in pieces of this many bytes (0: all at once)
 *   image per area (coils, discrete inputs, holding, input registers): start u16,
 *         count u8 % 17, then per address: state u8 (& 3 % 3 | & 4 writable), value u16
 *   answers n u8 % 8, each: kind u8 (bit0 an exception, else written / the pdu),
 *         code u8, length 1 + u8 % 253 and that many bytes (the forwarded reply PDU);
 *         used in turn for the requests handed to Python (none: exception 04)
 *   the rest: the stream (framed or raw, per ctl bit0)
 */
#include "../emb_serve.c"

#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>

#define FUZZ_NAME "fuzz_serve"
#include "fuzz_input.h"

#define NOW 1000000000LL /* the loop's clock, fixed */
#define CACHED_UNIT 1
#define FORWARD_UNIT 2
#define MAX_STREAM 8192
#define MAX_OUT (1 << 20)

/* emb_serve.c's clock (emb_engine.c's in the module) */
int64_t emb_now_ns(void)
{
    return NOW;
}

typedef struct {
    int exception;
    uint8_t code;
    uint8_t len;
    uint8_t pdu[256];
} answer;

static struct state {
    answer answers[8];
    unsigned n_answers, next_answer;
    struct {
        uint64_t request; /* its number (the server's requests counter) */
        answer a;
    } handed[MAX_STREAM / 8]; /* the requests handed to Python, in order */
    unsigned n_handed;
    uint8_t out[MAX_OUT]; /* what the server sent */
    size_t out_len;
    int peer;
} S;

static void drain(void)
{
    for (;;) {
        ssize_t got;

        if (S.out_len == MAX_OUT) {
            uint8_t sink[4096];
            got = recv(S.peer, sink, sizeof sink, MSG_DONTWAIT);
            CHECK(got <= 0); /* more output than any stream can ask for */
            return;
        }
        got = recv(S.peer, S.out + S.out_len, MAX_OUT - S.out_len, MSG_DONTWAIT);
        if (got <= 0)
            return;
        S.out_len += (size_t)got;
    }
}

/* Python's part: answer the request handed over (s->ev_*), as serve/server.py would. */
static void play_python(emb_server *s)
{
    int unit = s->ev_adu[6];
    answer none = {1, MODBUS_EXCEPTION_SLAVE_OR_SERVER_FAILURE, 0, {0}};
    const answer *a = S.n_answers ? &S.answers[S.next_answer++ % S.n_answers] : &none;
    int rc;

    CHECK(s->ev_len >= 8 && s->ev_len <= EMB_SV_ADU);
    CHECK(unit == CACHED_UNIT || unit == FORWARD_UNIT);
    CHECK(S.n_handed < sizeof S.handed / sizeof S.handed[0]);
    S.handed[S.n_handed].request = s->c.requests;
    S.handed[S.n_handed++].a = *a;
    if (a->exception)
        rc = emb_sv_post(s, s->ev_conn, s->ev_gen, EMB_SV_POST_EXCEPTION, &a->code, 1);
    else if (unit == CACHED_UNIT)
        rc = emb_sv_post(s, s->ev_conn, s->ev_gen, EMB_SV_POST_WRITTEN, NULL, 0);
    else
        rc = emb_sv_post(s, s->ev_conn, s->ev_gen, EMB_SV_POST_PDU, a->pdu, a->len);
    CHECK(rc == 1);
}

/* emb_sv_run's steps without poll(): flush posts, serve what is buffered, read. */
static void pump(emb_server *s)
{
    emb_sv_conn *c = &s->conns[0];

    for (;;) {
        uint32_t before;

        emb_sv_flush_posts(s, NOW);
        drain();
        if (emb_sv_serve_buffered(s, NOW)) {
            CHECK(c->busy);
            play_python(s);
            continue;
        }
        drain();
        if (c->fd < 0)
            return;
        CHECK(!c->busy);
        before = c->have;
        emb_sv_read(s, c);
        if (c->fd < 0 || c->have == before)
            return;
    }
}

static emb_server *make_server(int fd)
{
    emb_server *s = calloc(1, sizeof *s);

    if (s == NULL)
        return NULL;
    s->listen_fd = -1;
    s->max_conns = 1;
    s->conns = calloc(1, sizeof *s->conns);
    s->pfds = calloc(3, sizeof(struct pollfd));
    s->pidx = calloc(3, sizeof *s->pidx);
    s->wake_fd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    s->ctx = modbus_new_tcp("127.0.0.1", 502); /* frames replies only: never connects */
    pthread_mutex_init(&s->lock, NULL);
    if (s->conns == NULL || s->pfds == NULL || s->pidx == NULL || s->wake_fd < 0
        || s->ctx == NULL) {
        if (s->conns != NULL)
            s->conns[0].fd = -1;
        else
            s->max_conns = 0;
        emb_sv_free(s);
        return NULL;
    }
    modbus_set_response_timeout(s->ctx, 0, 1);
    s->conns[0].fd = fd;
    s->conns[0].gen = 1;
    return s;
}

/* The cached unit's image from the input. */
static void set_image(emb_server *s, reader *r, int fresh)
{
    int spans[8];
    emb_sv_run_op ops[4 * 16];
    uint16_t values[4 * 16];
    uint32_t n_ops = 0;

    for (int a = 0; a < 4; a++) {
        unsigned start = rd16(r), count = rd8(r) % 17;
        if (start + count > 65536)
            start = 65536 - count;
        spans[2 * a] = (int)start;
        spans[2 * a + 1] = (int)count;
        for (unsigned i = 0; i < count; i++) {
            uint8_t st = rd8(r);
            emb_sv_run_op *op = &ops[n_ops];

            op->unit = CACHED_UNIT;
            op->area = (uint8_t)a;
            op->state = (uint8_t)(((st & 3) % 3) | (st & EMB_SV_WRITABLE));
            op->start = (uint16_t)(start + i);
            op->count = 1;
            op->first = n_ops;
            values[n_ops++] = rd16(r);
        }
    }
    CHECK(emb_sv_unit_set(s, CACHED_UNIT, EMB_SV_CACHED, spans) == 0);
    CHECK(emb_sv_unit_set(s, FORWARD_UNIT, EMB_SV_FORWARD, spans) == 0);
    emb_sv_update(s, ops, n_ops, values);
    emb_sv_unit_fresh(s, CACHED_UNIT, fresh ? NOW + 1 : NOW - 1);
}

/* The stream: framed (valid headers) or raw. */
static size_t make_stream(reader *r, int framed, uint8_t *stream)
{
    size_t n = 0;
    unsigned tid = 0;

    if (!framed) {
        while (r->n > 0 && n < MAX_STREAM)
            stream[n++] = rd8(r);
        return n;
    }
    while (r->n > 0 && n + EMB_SV_ADU <= MAX_STREAM) {
        uint8_t unit = rd8(r);
        unsigned len = rd8(r) % 254;

        stream[n++] = (uint8_t)(tid >> 8);
        stream[n++] = (uint8_t)tid++;
        stream[n++] = 0;
        stream[n++] = 0;
        stream[n++] = (uint8_t)((len + 1) >> 8);
        stream[n++] = (uint8_t)(len + 1);
        stream[n++] = unit;
        for (unsigned i = 0; i < len; i++)
            stream[n++] = rd8(r);
    }
    return n;
}

/* The byte count a normal read reply must carry, or -1 for another function. */
static int read_bytes(const uint8_t *pdu)
{
    unsigned qty = (unsigned)pdu[3] << 8 | pdu[4];

    switch (pdu[0]) {
    case 1:
    case 2: return (int)((qty + 7) / 8);
    case 3:
    case 4: return (int)(2 * qty);
    default: return -1;
    }
}

/* Check S.out and the counters against the model of the stream. */
static void check_replies(const emb_server *s, const uint8_t *stream, size_t n)
{
    size_t pos = 0, out = 0;
    uint64_t requests = 0, cached = 0, exceptions = 0, got_exceptions = 0;
    unsigned handed = 0;
    int bad = 0;

    while (n - pos >= 6) {
        const uint8_t *req = stream + pos, *rep, *pdu, *rpdu;
        unsigned len = (unsigned)req[4] << 8 | req[5], rlen, plen;
        int unit;

        if (req[2] != 0 || req[3] != 0 || len < 2 || len > EMB_SV_MAX_LEN) {
            bad = 1;
            break;
        }
        if (n - pos < 6 + len)
            break;
        requests++;
        unit = req[6];
        pdu = req + EMB_SV_HDR;
        plen = len - 1;
        /* its reply */
        CHECK(S.out_len - out >= 6);
        rep = S.out + out;
        rlen = (unsigned)rep[4] << 8 | rep[5];
        CHECK(rep[0] == req[0] && rep[1] == req[1]); /* transaction id */
        CHECK(rep[2] == 0 && rep[3] == 0);
        CHECK(rlen >= 2 && S.out_len - out >= 6 + rlen);
        CHECK(rep[6] == unit);
        rpdu = rep + EMB_SV_HDR;
        if (handed < S.n_handed && S.handed[handed].request == requests) {
            const answer *a = &S.handed[handed++].a;

            CHECK(unit == FORWARD_UNIT || unit == CACHED_UNIT);
            if (a->exception) {
                CHECK(rlen == 3 && rpdu[0] == (pdu[0] | 0x80) && rpdu[1] == a->code);
                exceptions++;
            } else if (unit == FORWARD_UNIT) {
                CHECK(rlen == 1u + a->len && memcmp(rpdu, a->pdu, a->len) == 0);
                exceptions += a->len == 2 && (a->pdu[0] & 0x80) && a->pdu[1] < 12;
            } else {
                /* a confirmed write: FC05/06 echo the request, FC0F/10 its address and
                 * quantity (Application Protocol 1.1b3, 6.5, 6.6, 6.11, 6.12) */
                CHECK(plen >= 5 && (pdu[0] == 5 || pdu[0] == 6 || pdu[0] == 0x0F
                                    || pdu[0] == 0x10));
                CHECK(rlen == 6 && memcmp(rpdu, pdu, 5) == 0);
            }
        } else if (unit == FORWARD_UNIT) {
            CHECK(0); /* every request of a forward unit goes to Python */
        } else if (unit != CACHED_UNIT) {
            CHECK(rlen == 3 && rpdu[0] == (pdu[0] | 0x80)
                  && rpdu[1] == MODBUS_EXCEPTION_GATEWAY_PATH);
            exceptions++;
        } else if (rlen == 3 && (rpdu[0] & 0x80)) {
            /* the image refused it: our checks' codes only */
            CHECK(rpdu[0] == (pdu[0] | 0x80));
            CHECK(rpdu[1] == 1 || rpdu[1] == 2 || rpdu[1] == 3 || rpdu[1] == 0x0B);
            exceptions++;
        } else {
            /* a read answered from the image: its function, the byte count of its
             * quantity and that many bytes */
            int bytes = plen == 5 ? read_bytes(pdu) : -1;

            CHECK(bytes >= 0);
            CHECK(rpdu[0] == pdu[0] && rpdu[1] == bytes && rlen == 3u + (unsigned)bytes);
            cached++;
        }
        out += 6 + rlen;
        pos += 6 + len;
    }
    CHECK(handed == S.n_handed);
    CHECK(out == S.out_len); /* nothing else was sent */
    CHECK((s->conns[0].fd < 0) == bad);
    CHECK(s->c.closed_bad == (uint64_t)bad);
    CHECK(s->c.requests == requests);
    CHECK(s->c.cached_replies == cached);
    CHECK(s->c.to_python == S.n_handed);
    for (int k = 0; k < 12; k++)
        got_exceptions += s->c.exceptions[k];
    CHECK(got_exceptions == exceptions); /* libmodbus refused nothing by itself */
}

int LLVMFuzzerTestOneInput(const uint8_t *input, size_t size)
{
    static uint8_t stream[MAX_STREAM];
    reader r = {input, size};
    uint8_t ctl = rd8(&r);
    unsigned chunk = rd8(&r);
    int sv[2];
    emb_server *s;
    size_t n, at;

    memset(&S, 0, offsetof(struct state, out));
    S.out_len = 0;
    if (socketpair(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK, 0, sv) == -1)
        return 0;
    S.peer = sv[1];
    s = make_server(sv[0]);
    if (s == NULL) {
        close(sv[0]);
        close(sv[1]);
        return 0;
    }
    set_image(s, &r, ctl & 2);
    S.n_answers = rd8(&r) % 8;
    for (unsigned k = 0; k < S.n_answers; k++) {
        answer *a = &S.answers[k];

        a->exception = rd8(&r) & 1;
        a->code = (uint8_t)(1 + rd8(&r) % 11);
        a->len = (uint8_t)(1 + rd8(&r) % 253); /* a reply PDU has its function code */
        for (unsigned i = 0; i < a->len; i++)
            a->pdu[i] = rd8(&r);
    }
    n = make_stream(&r, ctl & 1, stream);
    for (at = 0; at < n && s->conns[0].fd >= 0;) {
        size_t piece = chunk ? chunk : n;

        if (piece > n - at)
            piece = n - at;
        CHECK(send(S.peer, stream + at, piece, MSG_NOSIGNAL) == (ssize_t)piece);
        at += piece;
        pump(s);
    }
    drain();
    check_replies(s, stream, n);
    close(S.peer);
    emb_sv_free(s); /* closes the server's end */
    return 0;
}
