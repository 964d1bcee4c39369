/* edgemodbus: transactions around libmodbus 3.1.6, one link kind for all.
 *
 * Each function does a whole step (drop stale input, send, skip an echo, receive, check)
 * so that the Python bus worker makes one C call, with the GIL released, per Modbus
 * transaction.  What differs per link kind (framing, receiving, what comes besides
 * replies) is the link's backend (csrc/emb_backend.h: plain RTU and Modbus TCP in
 * csrc/emb_rtu.c, DTU streams in csrc/emb_stream.c); every reply is checked here by the
 * one check, emb_check_reply (csrc/emb_check.c), because 3.1.6 does not make them all: it
 * loses undefined exception codes, ignores the MBAP unit id and length, and never checks
 * a write's echo.  No globals, no allocation: callers own every buffer. */
#include "emb_io.h"

#include <errno.h>
#include <string.h>

#include "emb_rtu.h"
#include "emb_stream.h"

/* -- the frame trace (emb_link.h emb_trace) ------------------------------------------ */

static void emb_trace_copy_in(emb_trace *t, const uint8_t *p, uint32_t n)
{
    uint32_t at = (t->head + t->used) % EMB_TRACE_SIZE;
    uint32_t first = n < EMB_TRACE_SIZE - at ? n : EMB_TRACE_SIZE - at;

    memcpy(t->buf + at, p, first);
    memcpy(t->buf, p + first, n - first);
    t->used += n;
}

static void emb_trace_copy_out(emb_trace *t, uint8_t *p, uint32_t n)
{
    uint32_t first = n < EMB_TRACE_SIZE - t->head ? n : EMB_TRACE_SIZE - t->head;

    memcpy(p, t->buf + t->head, first);
    memcpy(p + first, t->buf, n - first);
    t->head = (t->head + n) % EMB_TRACE_SIZE;
    t->used -= n;
}

/* Trace a frame of n bytes (at most EMB_MAX_ADU) sent (EMB_TRACE_TX) or received
 * (EMB_TRACE_RX) now, when the link is traced; a full ring loses it, counted. */
void emb_trace_put(emb_link *lk, int direction, const uint8_t *frame, int n)
{
    emb_trace *t = lk->trace;
    uint8_t head[EMB_TRACE_HEAD];
    int64_t now;

    if (t == NULL || n <= 0)
        return;
    if (n > EMB_MAX_ADU)
        n = EMB_MAX_ADU;
    if (EMB_TRACE_SIZE - t->used < (uint32_t)n + EMB_TRACE_HEAD) {
        t->lost++;
        return;
    }
    now = emb_now_ns();
    if (t->n == 0)
        t->first_ns = now;
    head[0] = (uint8_t)direction;
    head[1] = (uint8_t)(n >> 8);
    head[2] = (uint8_t)(n & 0xFF);
    memcpy(head + 3, &now, sizeof now);
    emb_trace_copy_in(t, head, EMB_TRACE_HEAD);
    emb_trace_copy_in(t, frame, (uint32_t)n);
    t->n++;
}

/* Take the oldest traced frame into out (at least EMB_MAX_ADU bytes), its direction and
 * time: its length, 0 when none waits. */
int emb_trace_take(emb_trace *t, uint8_t *out, int *direction, int64_t *t_ns)
{
    uint8_t head[EMB_TRACE_HEAD];
    uint32_t n;

    if (t->n == 0)
        return 0;
    emb_trace_copy_out(t, head, EMB_TRACE_HEAD);
    n = (uint32_t)(head[1] << 8 | head[2]);
    *direction = head[0];
    memcpy(t_ns, head + 3, sizeof *t_ns);
    emb_trace_copy_out(t, out, n);
    t->n--;
    return (int)n;
}

/* The link kind of lk, from the fields Python set on it (emb_link.h). */
static const emb_backend *emb_backend_of(const emb_link *lk)
{
    if (lk->mbap)
        return &emb_mbap_backend;
    if (lk->wrapped)
        return &emb_wrapped_backend;
    if (lk->hb_len > 0)
        return &emb_stream_backend;
    return &emb_rtu_backend;
}

static int emb_timeout_ms(modbus_t *ctx, int byte)
{
    uint32_t sec = 0, usec = 0;

    if (byte)
        modbus_get_byte_timeout(ctx, &sec, &usec);
    else
        modbus_get_response_timeout(ctx, &sec, &usec);
    return (int)(sec * 1000U + (usec + 999U) / 1000U);
}

/* Send pdu (function code first) to slave through the link's backend; the ADU put on
 * the wire goes to sent. */
static int emb_send_adu(modbus_t *ctx, emb_link *lk, const emb_backend *be, int slave,
                        const uint8_t *pdu, int pdu_len, uint8_t *sent, int *sent_len)
{
    if (pdu_len < 1 || pdu_len > EMB_MAX_ADU - EMB_MBAP || slave < 0 || slave > 255) {
        errno = EINVAL;
        return -1;
    }
    return be->send(ctx, lk, slave, pdu, pdu_len, sent, sent_len);
}

/* The one check of a received frame (len bytes in rsp) against the request: the
 * backend's header fields (MBAP), then emb_check_reply on the unit id and PDU.  0 with
 * *exc (-1, or an exception code), or the EMB_E* errno. */
static int emb_check(const emb_link *lk, const emb_backend *be, const uint8_t *req,
                     int req_len, const uint8_t *rsp, int len, int *exc)
{
    int h = be->header;
    int err;

    *exc = -1;
    if (len < h + 2)
        return EMB_ECOUNT;
    if (be->check_header && (err = be->check_header(lk, rsp, len)) != 0)
        return err;
    return emb_check_reply(req, req_len, rsp + h - 1, len - (h - 1) - be->trailer, exc);
}

/* What emb_check found, as a reader returns it: len for a normal reply, else -1 with
 * errno err, or EMB_EEXCEPTION + the code of an exception response. */
static int emb_checked(int err, int exc, int len)
{
    if (!err && exc >= 0)
        err = EMB_EEXCEPTION + exc;
    if (err) {
        errno = err;
        return -1;
    }
    return len;
}

/* Did what came back (got bytes) start with our own request? */
static int emb_looks_like_echo(const uint8_t *rsp, int got, const uint8_t *sent, int sent_len)
{
    int i = 0;

    while (i < sent_len && i < got && rsp[i] == sent[i])
        i++;
    return i >= 5 || (i == sent_len && i > 0);
}

/* An RTU reply that failed with err and starts with our own request: the line echoes
 * (the errors a reply check makes of an echo; a write's wrong echo is its own).  The
 * loop engine's links (csrc/emb_loop_link.c) name an echo with it too. */
int emb_echo_seen(int err, const uint8_t *rsp, int got, const uint8_t *sent,
                         int sent_len)
{
    if (err == ETIMEDOUT || err == EMB_EWECHO || err == EMB_ELENGTH)
        return err;
    return emb_looks_like_echo(rsp, got, sent, sent_len) ? EMB_EECHOSEEN : err;
}

/* One request and its checked reply (see emb_check); returns the reply ADU length
 * with the ADU in rsp, or -1 with errno (EMB_EEXCEPTION + code for an exception).
 * count: the byte count a wrapped reply must carry to be the answer (-1: any). */
static int emb_exchange(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu,
                        int pdu_len, int count, uint8_t *rsp)
{
    const emb_backend *be = emb_backend_of(lk);
    uint8_t req[EMB_MAX_ADU]; /* the unit id and the PDU, as emb_check_reply takes it */
    uint8_t sent[EMB_MAX_ADU];
    uint8_t next[EMB_MAX_ADU];
    int fd = modbus_get_socket(ctx);
    int byte_ms = emb_timeout_ms(ctx, 1);
    int echo_seen = be->skip_echo != NULL && !lk->echo;
    int64_t start;
    emb_want want;
    int sent_len = 0;
    int len, len2, err, err2, exc, exc2, got = 0, got2, extra, wait, skipped = 0;

    lk->rsp_len = 0;
    if (be->prepare(lk, fd) == -1)
        return -1;
    if (emb_send_adu(ctx, lk, be, slave, pdu, pdu_len, sent, &sent_len) == -1)
        return -1;
    emb_trace_put(lk, EMB_TRACE_TX, sent, sent_len);
    if (be->skip_echo && lk->echo &&
        be->skip_echo(lk, fd, sent, sent_len, emb_timeout_ms(ctx, 0), byte_ms) == -1)
        return -1;
    req[0] = (uint8_t)slave;
    memcpy(req + 1, pdu, (size_t)pdu_len);
    want.slave = slave;
    want.function = pdu[0];
    want.address = pdu_len >= 3 ? (pdu[1] << 8) | pdu[2] : -1;
    want.count = count;
    wait = emb_timeout_ms(ctx, 0); /* for the first byte: the response timeout */
    start = emb_now_ns();
    for (;;) {
        len = be->recv(lk, fd, &want, wait, byte_ms, rsp, &got);
        if (len <= 0) {
            err = len == 0 ? EMB_ESLAVE : errno;
            emb_trace_put(lk, EMB_TRACE_RX, rsp, got); /* what came, if anything */
            if (err == ETIMEDOUT && skipped)
                err = EMB_ETID; /* only replies to other requests came */
            if (echo_seen && err != ETIMEDOUT)
                err = emb_echo_seen(err, rsp, got, sent, sent_len);
            errno = err;
            return -1;
        }
        emb_trace_put(lk, EMB_TRACE_RX, rsp, len);
        err = emb_check(lk, be, req, pdu_len + 1, rsp, len, &exc);
        if (err != EMB_ETID)
            break;
        /* Modbus TCP: a reply to an earlier request (its transaction id says so) is
         * skipped and ours is awaited for the rest of the response timeout; what was
         * read behind it is the start of what came next (emb_backend.recv). */
        lk->discarded += len;
        skipped++;
        got -= len;
        memmove(rsp, rsp + len, (size_t)got);
        wait = emb_timeout_ms(ctx, 0) - (int)((emb_now_ns() - start) / 1000000);
        if (wait <= 0) {
            errno = EMB_ETID;
            return -1;
        }
    }
    /* Another whole frame right behind this one (a DTU that held a late reply and sends
     * it with the next one, or repeats a reply): the last answer to this request wins,
     * so a stale reply to an earlier request is never taken for this one.  Behind it:
     * the bytes the receiver read past the frame (a socket's greedy read), else those
     * waiting in the link (emb_backend.pending). */
    extra = got > len ? got - len : 0;
    if (be->min_next > 0 &&
        (extra ? extra : be->pending(lk, fd)) >= be->min_next) {
        memcpy(next, rsp + len, (size_t)extra);
        got2 = extra;
        len2 = be->recv(lk, fd, &want, 0, byte_ms, next, &got2);
        emb_trace_put(lk, EMB_TRACE_RX, next, len2 > 0 ? len2 : got2);
        if (len2 > 0) {
            err2 = emb_check(lk, be, req, pdu_len + 1, next, len2, &exc2);
            if (err2 == 0) {
                lk->discarded += len;
                memcpy(rsp, next, (size_t)len2);
                len = len2;
                err = 0;
                exc = exc2;
            } else {
                lk->discarded += len2;
            }
            lk->discarded += got2 - len2; /* read past the second frame: stale input */
        } else {
            lk->discarded += got2; /* another slave's frame, or a bad one */
        }
    } else {
        lk->discarded += extra; /* too few to be a frame: stale input, as if dropped by
                                 * the next request's prepare */
    }
    lk->rsp_len = len; /* also when rejected: the caller may show why */
    if (err && echo_seen)
        err = emb_echo_seen(err, rsp, len, sent, sent_len);
    return emb_checked(err, exc, len);
}

/* Read one block with function code 1, 2, 3 or 4 (Modbus Application Protocol
 * v1.1b3, 6.1-6.4) into dest: nb bytes (bits, one per byte) or nb registers.  rsp
 * (at least 260 bytes) receives the reply ADU.  Returns nb, or -1 with errno. */
int emb_read(modbus_t *ctx, emb_link *lk, int slave, int function, int addr, int nb,
             void *dest, uint8_t *rsp)
{
    uint8_t pdu[5];
    const uint8_t *data;
    int bits = function == 1 || function == 2;
    int max = bits ? MODBUS_MAX_READ_BITS : MODBUS_MAX_READ_REGISTERS;
    int count = bits ? (nb + 7) / 8 : 2 * nb;
    int i;

    if (function < 1 || function > 4 || nb < 1 || nb > max || addr < 0 || addr > 0xFFFF) {
        errno = EINVAL;
        return -1;
    }
    pdu[0] = (uint8_t)function;
    pdu[1] = (uint8_t)(addr >> 8);
    pdu[2] = (uint8_t)(addr & 0xFF);
    pdu[3] = (uint8_t)(nb >> 8);
    pdu[4] = (uint8_t)(nb & 0xFF);
    if (emb_exchange(ctx, lk, slave, pdu, 5, count, rsp) == -1)
        return -1;
    data = rsp + emb_backend_of(lk)->header + 2;
    if (bits) {
        uint8_t *out = (uint8_t *)dest;

        for (i = 0; i < nb; i++) /* first bit in the low bit of the first byte (6.1) */
            out[i] = (uint8_t)((data[i / 8] >> (i % 8)) & 1);
    } else {
        uint16_t *out = (uint16_t *)dest;

        for (i = 0; i < nb; i++) /* big-endian registers (4.2) */
            out[i] = (uint16_t)((data[2 * i] << 8) | data[2 * i + 1]);
    }
    return nb;
}

/* Send a request PDU (function code first) to slave and receive its reply ADU into
 * rsp (at least 260 bytes), checked as every reply (emb_check_reply: the header, the
 * function, a read's byte count, a write's echo, the length); exception responses are
 * returned as errors.  Returns the ADU length, or -1 with errno. */
int emb_transact(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                 uint8_t *rsp)
{
    return emb_exchange(ctx, lk, slave, pdu, pdu_len, -1, rsp);
}

/* emb_transact with a response timeout of its own (timeout_ms >= 0; the context's
 * comes back after it, so the caller's and the engine's idea of it stays true) and
 * broadcast (slave 0: sent, no reply; returns 0): one C call for a request that Python
 * holds whole (a forwarded one: csrc/emb_check.c checks FC23's byte count too). */
int emb_request(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                int timeout_ms, uint8_t *rsp)
{
    uint32_t sec = 0, usec = 0;
    int rc, err;

    if (slave == 0)
        return emb_send(ctx, lk, 0, pdu, pdu_len);
    if (timeout_ms < 0)
        return emb_exchange(ctx, lk, slave, pdu, pdu_len, -1, rsp);
    modbus_get_response_timeout(ctx, &sec, &usec);
    if (modbus_set_response_timeout(ctx, (uint32_t)timeout_ms / 1000U,
                                    (uint32_t)timeout_ms % 1000U * 1000U) == -1)
        return -1;
    rc = emb_exchange(ctx, lk, slave, pdu, pdu_len, -1, rsp);
    err = errno;
    modbus_set_response_timeout(ctx, sec, usec);
    errno = err;
    return rc;
}

/* Encode a write into pdu (at least EMB_MAX_ADU bytes): FC05 (nb 1; values[0] != 0 is
 * ON, sent as 0xFF00), FC06 (nb 1), FC15 (nb coils, each values[i] != 0 is ON, packed
 * first coil in the low bit), FC16 (nb registers), FC22 (nb 2: the AND and the OR mask).
 * Modbus Application Protocol v1.1b3, 6.5, 6.6, 6.11, 6.12, 6.16.  Its length, or -1
 * (EINVAL) for a function, address or quantity the protocol does not allow. */
int emb_write_pdu(int function, int addr, int nb, const uint16_t *values, uint8_t *pdu)
{
    int i, n;

    if (addr < 0 || addr > 0xFFFF)
        goto bad;
    pdu[0] = (uint8_t)function;
    pdu[1] = (uint8_t)(addr >> 8);
    pdu[2] = (uint8_t)(addr & 0xFF);
    switch (function) {
    case 5:
    case 6:
        if (nb != 1)
            goto bad;
        n = function == 5 ? (values[0] ? 0xFF00 : 0x0000) : values[0];
        pdu[3] = (uint8_t)(n >> 8);
        pdu[4] = (uint8_t)(n & 0xFF);
        return 5;
    case 15:
        if (nb < 1 || nb > MODBUS_MAX_WRITE_BITS)
            goto bad;
        n = (nb + 7) / 8;
        pdu[3] = (uint8_t)(nb >> 8);
        pdu[4] = (uint8_t)(nb & 0xFF);
        pdu[5] = (uint8_t)n;
        memset(pdu + 6, 0, (size_t)n);
        for (i = 0; i < nb; i++)
            if (values[i])
                pdu[6 + i / 8] |= (uint8_t)(1U << (i % 8));
        return 6 + n;
    case 16:
        if (nb < 1 || nb > MODBUS_MAX_WRITE_REGISTERS)
            goto bad;
        pdu[3] = (uint8_t)(nb >> 8);
        pdu[4] = (uint8_t)(nb & 0xFF);
        pdu[5] = (uint8_t)(2 * nb);
        for (i = 0; i < nb; i++) { /* big-endian registers (4.2) */
            pdu[6 + 2 * i] = (uint8_t)(values[i] >> 8);
            pdu[7 + 2 * i] = (uint8_t)(values[i] & 0xFF);
        }
        return 6 + 2 * nb;
    case 22:
        if (nb != 2)
            goto bad;
        for (i = 0; i < 2; i++) {
            pdu[3 + 2 * i] = (uint8_t)(values[i] >> 8);
            pdu[4 + 2 * i] = (uint8_t)(values[i] & 0xFF);
        }
        return 7;
    default:
        break;
    }
bad:
    errno = EINVAL;
    return -1;
}

/* A write in one C call: encoded (emb_write_pdu) into req, which keeps the request for
 * the caller's error message, then sent and its reply received and checked as every
 * reply (emb_check_reply: the echo of FC05/06/15/16/22, FC16's and FC15's quantity);
 * timeout_ms and slave 0 as emb_request.  Returns the reply ADU length (0: broadcast),
 * or -1 with errno (EMB_EEXCEPTION + code for an exception response). */
int emb_write(modbus_t *ctx, emb_link *lk, int slave, int function, int addr, int nb,
              const uint16_t *values, int timeout_ms, uint8_t *req, uint8_t *rsp)
{
    int len = emb_write_pdu(function, addr, nb, values, req);

    if (len == -1)
        return -1;
    return emb_request(ctx, lk, slave, req, len, timeout_ms, rsp);
}

/* Send without waiting for a reply: broadcast (slave 0) requests get none
 * (Modbus over Serial Line v1.02, 2.1).  An echo is still read back. */
int emb_send(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len)
{
    const emb_backend *be = emb_backend_of(lk);
    uint8_t sent[EMB_MAX_ADU];
    int fd = modbus_get_socket(ctx);
    int sent_len = 0;

    lk->rsp_len = 0;
    if (be->prepare(lk, fd) == -1)
        return -1;
    if (emb_send_adu(ctx, lk, be, slave, pdu, pdu_len, sent, &sent_len) == -1)
        return -1;
    emb_trace_put(lk, EMB_TRACE_TX, sent, sent_len);
    if (be->skip_echo && lk->echo &&
        be->skip_echo(lk, fd, sent, sent_len, emb_timeout_ms(ctx, 0),
                      emb_timeout_ms(ctx, 1)) == -1)
        return -1;
    return 0;
}

/* Read what is readable now, without waiting, and frame it (a stream link: reports
 * queued, heartbeats counted; any other link: stale input dropped, counted in
 * lk->discarded).  The line worker calls it while idle.  Returns the reports waiting in
 * the ring, or -1 with errno when the link failed or the peer closed it (EINVAL: a
 * stream link without its buffers). */
long emb_pump(modbus_t *ctx, emb_link *lk)
{
    return emb_backend_of(lk)->pump(lk, modbus_get_socket(ctx));
}

/* Bytes that came on the link's socket before the link was made (what a DTU sent after
 * its registration), taken as if received now, nothing having been asked: framed on a
 * stream link, dropped (counted in lk->discarded) on any other.  Returns the reports
 * waiting (-1, EINVAL: a stream link without its buffers). */
long emb_feed(emb_link *lk, const uint8_t *data, int n)
{
    return emb_backend_of(lk)->feed(lk, data, n < 0 ? 0 : n);
}

/* Settle or drain a link (emb_discard_input's timing): a stream link frames what comes,
 * any other drops it.  Returns the bytes dropped, or -1 with errno. */
long emb_link_discard(modbus_t *ctx, emb_link *lk, int total_ms, int quiet_ms, int limit_ms)
{
    return emb_backend_of(lk)->discard(lk, modbus_get_socket(ctx), total_ms, quiet_ms,
                                       limit_ms);
}
