/* edgemodbus: a loop link's non-blocking I/O (see emb_loop_io.h).
 *
 * The framing is the blocking backends' (csrc/emb_backend.h), on reads that never wait:
 * a DTU stream's bytes go into its buffer and are framed there (csrc/emb_stream.c: plain
 * RTU with heartbeats, the request's own bytes first with the echo option; wrapped frames,
 * every frame but the reply queued as a report); a Modbus TCP reply is read as far as its
 * header tells (emb_reply_length), a reply to another transaction id skipped (Modbus
 * Messaging on TCP/IP v1.0b, 3.1.3).  Every frame sent and received goes to the link's
 * trace ring (csrc/emb_io.c emb_trace_put), as in the blocking engine.  No globals, no
 * allocation: the buffers are the link's. */
#include "emb_loop_io.h"

#include <errno.h>
#include <string.h>
#include <sys/socket.h>

#include "emb_io.h" /* emb_trace_put */
#include "emb_rtu.h"
#include "emb_stream.h"

#define EMB_LL_WRAP 4 /* a wrapped request: FF AA and the register address before the RTU
                       * frame, 0D after it (csrc/emb_stream.c) */

/* Bytes of a reply ADU before its function code, and after its PDU (emb_backend.h). */
int emb_ll_header(const emb_link *lk)
{
    return lk->mbap ? EMB_MBAP : 1;
}

int emb_ll_trailer(const emb_link *lk)
{
    return lk->mbap ? 0 : 2;
}

/* Put the request in k->req on the wire format of the link (k->wire): an RTU frame, a
 * wrapped one, or an MBAP header with the link's next transaction id.  0, or -1. */
int emb_ll_frame(emb_loop_link *k)
{
    emb_link *lk = k->e->lk;
    int len = 0;

    if (lk->mbap) {
        lk->tid = (lk->tid + 1U) & 0xFFFFU;
        k->wire[0] = (uint8_t)(lk->tid >> 8);
        k->wire[1] = (uint8_t)(lk->tid & 0xFF);
        k->wire[2] = 0;
        k->wire[3] = 0;
        k->wire[4] = (uint8_t)(k->req_len >> 8); /* the unit id and the PDU */
        k->wire[5] = (uint8_t)(k->req_len & 0xFF);
        memcpy(k->wire + 6, k->req, (size_t)k->req_len);
        k->wire_len = 6 + k->req_len;
        return 0;
    }
    if (!lk->wrapped)
        return emb_rtu_frame(k->req[0], k->req + 1, k->req_len - 1, k->wire, &k->wire_len);
    if (emb_rtu_frame(k->req[0], k->req + 1, k->req_len - 1, k->wire + EMB_LL_WRAP, &len) == -1)
        return -1;
    k->wire[0] = 0xFF;
    k->wire[1] = 0xAA;
    k->wire[2] = k->req[2]; /* the register address */
    k->wire[3] = k->req[3];
    k->wire[EMB_LL_WRAP + len] = 0x0D;
    k->wire_len = len + EMB_LL_WRAP + 1;
    return 0;
}

/* Send what is left of the request.  0: it is out (the reply is awaited from now on);
 * 1: the send buffer is full (the rest when the socket is writable); -1 with errno. */
int emb_ll_push(emb_loop *lp, emb_loop_link *k, int64_t now)
{
    emb_link *lk = k->e->lk;
    ssize_t n;

    while (k->sent < k->wire_len) {
        n = send(k->fd, k->wire + k->sent, (size_t)(k->wire_len - k->sent),
                 MSG_NOSIGNAL | MSG_DONTWAIT);
        if (n > 0) {
            k->sent += (int)n;
            continue;
        }
        if (n == -1 && errno == EINTR)
            continue;
        if (n == -1 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            if (!k->want_out && emb_loop_watch(lp, k->fd, k->slot, 1) == -1)
                return -1;
            k->want_out = 1;
            return 1;
        }
        return -1;
    }
    if (k->want_out && emb_loop_watch(lp, k->fd, k->slot, 0) == -1)
        return -1;
    k->want_out = 0;
    if (lk->wrapped) /* the trace shows the RTU frame inside, as csrc/emb_io.c */
        emb_trace_put(lk, EMB_TRACE_TX, k->wire + EMB_LL_WRAP, k->wire_len - EMB_LL_WRAP - 1);
    else
        emb_trace_put(lk, EMB_TRACE_TX, k->wire, k->wire_len);
    k->start_ns = now;
    k->last_ns = 0;
    k->got = 0;
    k->skipped = 0;
    k->echo_left = lk->echo && !lk->wrapped && !lk->mbap;
    k->state = EMB_LS_AWAIT;
    return 0;
}

/* Take in what a stream link's socket holds: the bytes read, or -1 with errno. */
static int emb_ll_fill(emb_loop_link *k)
{
    int rc, total = 0;

    while ((rc = emb_stream_fill(k->e->lk, k->fd)) > 0)
        total += rc;
    return rc == -1 ? -1 : total;
}

/* What came while no reply is awaited (idle, sending, settling): a stream link frames it
 * (wrapped reports queued, heartbeats counted, stale bytes dropped), a Modbus TCP link
 * drops it (as its blocking prepare and discard).  The bytes dropped, or -1 with errno;
 * *came: whether bytes came. */
long emb_ll_absorb(emb_loop_link *k, int *came)
{
    long n;
    int rc;

    if (k->e->lk->mbap) {
        n = emb_discard_input(k->fd, 0, 0, 0);
        *came = n > 0;
        return n;
    }
    rc = emb_ll_fill(k);
    *came = rc > 0;
    return rc == -1 ? -1 : emb_stream_take_idle(k->e->lk);
}

/* Modbus TCP: read a reply into buf (*have bytes of it so far) as far as its header tells,
 * never past its end (what follows stays in the socket, as csrc/emb_rtu.c reads).  Its
 * length when whole, EMB_STREAM_MORE, or -1 with errno (EMBBADDATA, the link's). */
static int emb_ll_mbap_read(int fd, uint8_t *buf, int *have)
{
    ssize_t n;
    int need;

    for (;;) {
        need = emb_reply_length(buf, *have, 1);
        if (need < 0) {
            errno = EMBBADDATA;
            return -1;
        }
        if (*have >= need)
            return need;
        n = emb_read_some(fd, buf + *have, (size_t)(need - *have));
        if (n < 0)
            return -1;
        if (n == 0)
            return EMB_STREAM_MORE;
        *have += (int)n;
    }
}

/* What the reply awaited must be (a wrapped link's receiver picks it by these). */
static void emb_ll_want(const emb_loop_link *k, emb_want *w)
{
    const emb_device *d = k->e->devices[k->which];
    const emb_eblock *b = &d->blocks[d->pass_list[d->index]];

    w->slave = d->slave;
    w->function = b->function;
    w->address = b->start;
    w->count = b->function <= 2 ? (b->count + 7) / 8 : 2 * b->count;
}

/* Frame the reply awaited from what the socket holds: its length in e->rsp (whole,
 * integrity checked), 0 for a frame that answers nothing (another slave's, or a Modbus TCP
 * reply to another transaction id: skipped), EMB_STREAM_MORE, or -1 with errno.  *got:
 * the bytes taken. */
int emb_ll_take(emb_loop_link *k, int64_t now, int *got)
{
    emb_engine *e = k->e;
    emb_link *lk = e->lk;
    emb_want want;
    int rc, before = k->got;

    *got = 0;
    if (lk->mbap) {
        rc = emb_ll_mbap_read(k->fd, e->rsp, &k->got);
        if (k->got > before)
            k->last_ns = now;
        *got = k->got;
        if (rc < 0)
            return rc;
        k->got = 0;
        if (emb_check_mbap(e->rsp, rc, (long)lk->tid) != EMB_ETID)
            return rc;
        emb_trace_put(lk, EMB_TRACE_RX, e->rsp, rc);
        lk->discarded += rc; /* ours is awaited for the rest of the response timeout */
        k->skipped++;
        *got = 0;
        return 0;
    }
    rc = emb_ll_fill(k);
    if (rc == -1)
        return -1;
    if (rc > 0)
        k->last_ns = now;
    if (lk->wrapped) { /* the frames besides the reply are queued as reports */
        emb_ll_want(k, &want);
        rc = emb_wrapped_backend.recv(lk, k->fd, &want, 0, 0, e->rsp, got);
        return rc == -1 && errno == ETIMEDOUT ? EMB_STREAM_MORE : rc;
    }
    if (k->echo_left) {
        if (emb_stream_backend.skip_echo(lk, k->fd, k->wire, k->wire_len, 0, 0) == -1)
            return errno == ETIMEDOUT || errno == EMB_EPARTIAL ? EMB_STREAM_MORE : -1;
        k->echo_left = 0;
        k->start_ns = now; /* the reply's own timeout from here on, as csrc/emb_io.c */
        k->last_ns = 0;
    }
    return emb_stream_try(lk, e->devices[k->which]->slave, e->rsp, got);
}

/* Bytes of a reply received and not framed yet (heartbeats aside). */
int emb_ll_pending(emb_loop_link *k)
{
    return k->e->lk->mbap ? k->got : emb_stream_backend.pending(k->e->lk, k->fd);
}

/* The reply's deadline: the response timeout until bytes of it came, then the byte
 * timeout from the last ones (as the blocking receivers; a wrapped reply: the response
 * timeout, as csrc/emb_stream.c emb_wrapped_recv). */
int64_t emb_ll_reply_due(emb_loop_link *k)
{
    const emb_device *d = k->e->devices[k->which];
    emb_link *lk = k->e->lk;

    if (!lk->wrapped && k->last_ns && k->byte_ms > 0 && emb_ll_pending(k) > 0)
        return k->last_ns + (int64_t)k->byte_ms * 1000000; /* heartbeats do not count */
    return k->start_ns + (int64_t)d->timeout_ms * 1000000;
}

/* Frame a second frame behind the reply into k->next, as emb_ll_take frames the reply
 * (a Modbus TCP one read as far as its header tells, k->got2 bytes so far; one with
 * another transaction id answers nothing: 0). */
static int emb_ll_take_next(emb_loop_link *k, int64_t now, int *got)
{
    emb_link *lk = k->e->lk;
    int rc, before = k->got2;

    *got = 0;
    if (lk->mbap) {
        rc = emb_ll_mbap_read(k->fd, k->next, &k->got2);
        if (k->got2 > before)
            k->last_ns = now;
        *got = k->got2;
        return rc > 0 && emb_check_mbap(k->next, rc, (long)lk->tid) != 0 ? 0 : rc;
    }
    rc = emb_ll_fill(k);
    if (rc == -1)
        return -1;
    if (rc > 0)
        k->last_ns = now;
    return emb_stream_try(lk, k->e->devices[k->which]->slave, k->next, got);
}

/* The last answer wins, as in the blocking receive (csrc/emb_io.c: a DTU that held a
 * late reply sends it with the next one; a Modbus TCP peer that repeats a reply): a
 * frame behind the reply (k->first_len bytes in e->rsp) that answers the request
 * replaces it; one still arriving (at least a header's worth came) is waited for up to
 * the byte timeout from its last bytes (EMB_LS_NEXT), then given up (its bytes are stale
 * before the next request).  Wrapped links take the first answer (the frames behind it
 * are reports).  1 while it waits (its deadline set), else 0: the reply is decided
 * (k->first_len bytes in e->rsp). */
int emb_ll_last_answer(emb_loop *lp, emb_loop_link *k, int64_t now)
{
    emb_engine *e = k->e;
    emb_link *lk = e->lk;
    int len2, got2 = 0, exc = -1, err, h = emb_ll_header(lk);
    int64_t until;

    if (k->state != EMB_LS_NEXT) {
        if (lk->wrapped || (lk->mbap ? emb_pending(k->fd) < EMB_MBAP + 2
                                     : emb_ll_pending(k) < 5))
            return 0;
        k->got2 = 0;
        k->last_ns = now;
    }
    len2 = emb_ll_take_next(k, now, &got2);
    err = errno;
    if (len2 == EMB_STREAM_MORE) {
        until = k->last_ns + (int64_t)k->byte_ms * 1000000;
        if (now < until) {
            k->state = EMB_LS_NEXT;
            emb_timer_set(lp, k->slot, until);
            return 1;
        }
        k->state = EMB_LS_AWAIT; /* it stopped short */
        if (lk->mbap) {
            emb_trace_put(lk, EMB_TRACE_RX, k->next, got2);
            lk->discarded += got2;
        }
        return 0;
    }
    k->state = EMB_LS_AWAIT;
    emb_trace_put(lk, EMB_TRACE_RX, k->next, len2 > 0 ? len2 : got2);
    if (len2 > 0 && emb_check_reply(k->req, k->req_len, k->next + h - 1,
                                    len2 - (h - 1) - emb_ll_trailer(lk), &exc) == 0) {
        lk->discarded += k->first_len;
        memcpy(e->rsp, k->next, (size_t)len2);
        k->first_len = len2;
        return 0;
    }
    if (len2 >= 0 || lk->mbap || err != EMBBADDATA) /* a stream's bad bytes stay in rx */
        lk->discarded += len2 > 0 ? len2 : got2;
    return 0;
}
