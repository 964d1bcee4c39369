/* edgemodbus: DTU streams, framed byte for byte in C.
 *
 * A stream link is RTU over a socket on which a DTU (or an edge MCU behind one) sends
 * more than replies; two link kinds (csrc/emb_backend.h): emb_stream_backend (plain RTU
 * with heartbeats) and emb_wrapped_backend:
 *
 * - heartbeats (lk->hb, e.g. "HB" or FE) on an idle link, which can also arrive between a
 *   request and its reply: skipped wherever a frame could begin, and counted;
 * - wrapped frames (lk->wrapped): FF AA | register address (2 bytes, big-endian) | RTU
 *   frame with its CRC | 0D.  Requests go out wrapped (csrc/emb_io.c); the reply is the
 *   frame with the request's slave, function and address and, for a read, its byte count;
 *   every other valid frame is an unsolicited report, queued in the link's ring for the
 *   caller (emb_report_take) whether it came before the reply, behind it, during a settle
 *   or while the link was idle (emb_pump).  Bad frames are dropped and counted, parsing
 *   resynchronises on the next header: the rules of src/edgemodbus/protocol/wrapped.py
 *   (ReportParser), which the simulator keeps using.
 *
 * Bytes are read into lk->sb->rx, as many as are readable, and framed from there; what is
 * left (a frame not complete yet) waits there for the next read.  No globals, no
 * allocation: the buffers are in the link. */
#include "emb_stream.h"

#include <errno.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

#include "emb_check.h"
#include "emb_rtu.h" /* emb_rtu_frame, emb_rtu_send: a stream's requests are RTU frames */
#include "emb_util.h"

#define EMB_WRAP_PREFIX 4 /* FF AA and the register address */
#define EMB_WRAP_TAIL 0x0D
#define EMB_PUMP_READS 64
#define EMB_WRAPPED_REQ_MAX (4 + EMB_MAX_RTU + 1) /* FF AA, address, RTU frame, 0D */ /* emb_pump: at most this many reads (a flooding peer) */

/* A stream link needs its buffers (lk->sb, and lk->ring when wrapped): 0 with errno
 * EINVAL if they are missing. */
static int emb_has_buffers(const emb_link *lk)
{
    if (lk->sb != NULL && (!lk->wrapped || lk->ring != NULL))
        return 1;
    errno = EINVAL;
    return 0;
}

/* -- the report ring: per report a 2-byte length (big-endian) and the wrapped frame -- */

static void emb_ring_put(emb_link *lk, const uint8_t *p, uint32_t n)
{
    uint32_t at = (lk->ring_head + lk->ring_used) % EMB_RING_SIZE;
    uint32_t first = n < EMB_RING_SIZE - at ? n : EMB_RING_SIZE - at;

    memcpy(lk->ring + at, p, first);
    memcpy(lk->ring, p + first, n - first);
    lk->ring_used += n;
}

static void emb_ring_get(emb_link *lk, uint8_t *p, uint32_t n)
{
    uint32_t first = n < EMB_RING_SIZE - lk->ring_head ? n : EMB_RING_SIZE - lk->ring_head;

    memcpy(p, lk->ring + lk->ring_head, first);
    memcpy(p + first, lk->ring, n - first);
    lk->ring_head = (lk->ring_head + n) % EMB_RING_SIZE;
    lk->ring_used -= n;
}

/* Queue a report (a whole wrapped frame); a full ring loses it, counted. */
static void emb_report_put(emb_link *lk, const uint8_t *frame, uint32_t n)
{
    uint8_t len[2];

    if (EMB_RING_SIZE - lk->ring_used < n + 2) {
        lk->reports_lost++;
        return;
    }
    len[0] = (uint8_t)(n >> 8);
    len[1] = (uint8_t)(n & 0xFF);
    emb_ring_put(lk, len, 2);
    emb_ring_put(lk, frame, n);
    lk->n_reports++;
}

/* Take the oldest report into out (at least EMB_REPORT_MAX bytes): the whole wrapped
 * frame, already checked (header, length, tail, CRC).  Returns its length, 0 if none
 * waits. */
int emb_report_take(emb_link *lk, uint8_t *out)
{
    uint8_t len[2];
    uint32_t n;

    if (lk->n_reports == 0)
        return 0;
    emb_ring_get(lk, len, 2);
    n = (uint32_t)(len[0] << 8 | len[1]);
    emb_ring_get(lk, out, n);
    lk->n_reports--;
    if (lk->n_before > 0)
        lk->n_before--;
    return (int)n;
}

/* Copy the report *at bytes past the oldest one (0: the oldest) into out (at least
 * EMB_REPORT_MAX bytes) without taking it; *at moves to the next.  Returns its length.
 * The caller reads at most lk->n_reports of them (csrc/emb_report.c). */
int emb_report_peek(const emb_link *lk, uint32_t *at, uint8_t *out)
{
    uint32_t pos = (lk->ring_head + *at) % EMB_RING_SIZE, n, i;

    n = (uint32_t)(lk->ring[pos] << 8 | lk->ring[(pos + 1) % EMB_RING_SIZE]);
    for (i = 0; i < n; i++)
        out[i] = lk->ring[(pos + 2 + i) % EMB_RING_SIZE];
    *at += n + 2;
    return (int)n;
}

/* -- the receive buffer ------------------------------------------------------------- */

static void emb_rx_consume(emb_link *lk, uint32_t n)
{
    memmove(lk->sb->rx, lk->sb->rx + n, lk->rx_len - n);
    lk->rx_len -= n;
}

/* Read what is readable on fd into lk->sb->rx (up to its free space), waiting until
 * deadline_ns for it (a deadline passed: only what is there now).  Returns the bytes
 * read, 0 if none came in time, -1 with errno (end of file: emb_eof_errno). */
static int emb_rx_fill(emb_link *lk, int fd, int64_t deadline_ns)
{
    uint32_t space = EMB_RX_SIZE - lk->rx_len;
    ssize_t n;
    int rc;

    if (space == 0)
        return 0;
    for (;;) {
        rc = emb_wait_until(fd, deadline_ns);
        if (rc <= 0)
            return rc;
        n = emb_read_some(fd, lk->sb->rx + lk->rx_len, space);
        if (n < 0)
            return -1;
        if (n > 0) {
            lk->rx_len += (uint32_t)n;
            return (int)n;
        }
    }
}

/* How many trailing bytes of rx are a proper prefix of the heartbeat (it may go on). */
static uint32_t emb_hb_partial(const emb_link *lk)
{
    uint32_t n = lk->hb_len ? lk->hb_len - 1 : 0;

    if (n > lk->rx_len)
        n = lk->rx_len;
    for (; n > 0; n--)
        if (memcmp(lk->sb->rx + lk->rx_len - n, lk->hb, n) == 0)
            return n;
    return 0;
}

/* Count and remove the heartbeats at the start of rx.  Returns 1 if rx then holds only
 * the beginning of another one (more bytes may complete it). */
static int emb_hb_strip(emb_link *lk)
{
    uint32_t h = lk->hb_len;

    if (h == 0)
        return 0;
    while (lk->rx_len >= h && memcmp(lk->sb->rx, lk->hb, h) == 0) {
        emb_rx_consume(lk, h);
        lk->heartbeats++;
    }
    return lk->rx_len > 0 && lk->rx_len < h && memcmp(lk->sb->rx, lk->hb, lk->rx_len) == 0;
}

/* Plain RTU stream, nothing asked: heartbeats anywhere in rx are counted, every other
 * byte is stale and dropped, a heartbeat's beginning at the end too (kept, a stale byte
 * that happens to begin one would spoil the next reply).  Returns the bytes dropped. */
static long emb_plain_idle(emb_link *lk)
{
    uint32_t h = lk->hb_len, i = 0;
    long dropped = 0;

    while (i < lk->rx_len) {
        if (h && i + h <= lk->rx_len && memcmp(lk->sb->rx + i, lk->hb, h) == 0) {
            lk->heartbeats++;
            i += h;
        } else {
            dropped++;
            i++;
        }
    }
    lk->rx_len = 0;
    return dropped;
}

/* -- wrapped frames ------------------------------------------------------------------- */

/* Length of the RTU frame inside a wrapped frame at rx[0] (from its function code and
 * byte count: Application Protocol v1.1b3, ch. 6), -1 if more bytes are needed to tell,
 * 0 if it cannot be a reply (protocol/wrapped.py _rtu_length). */
static int emb_wrapped_rtu_length(const emb_link *lk)
{
    const uint8_t *p = lk->sb->rx + EMB_WRAP_PREFIX;
    int fc, count;

    if (lk->rx_len < EMB_WRAP_PREFIX + 2)
        return -1;
    fc = p[1];
    if (fc & 0x80)
        return 5; /* slave, function, exception code, CRC */
    if (fc >= 1 && fc <= 4) {
        if (lk->rx_len < EMB_WRAP_PREFIX + 3)
            return -1;
        count = p[2];
        if (count == 0 || (fc >= 3 && count % 2))
            return 0;
        return 3 + count + 2;
    }
    if (fc == 5 || fc == 6 || fc == 15 || fc == 16)
        return 8; /* slave, function, address, value or quantity, CRC */
    if (fc == 22)
        return 10;
    return 0;
}

static void emb_drop(emb_link *lk, const uint8_t *raw, uint32_t n)
{
    lk->dropped++;
    lk->last_drop_len = (int)(n < EMB_DROP_SHOW ? n : EMB_DROP_SHOW);
    memcpy(lk->last_drop, raw, (size_t)lk->last_drop_len);
}

/* Drop the frame at rx[0] (the first n_show bytes are shown): count it, skip its
 * header only (a real header may follow inside it); its rest, up to `end` if known
 * (else up to the next header), is not counted again. */
static void emb_bad(emb_link *lk, uint32_t n_show, int end)
{
    emb_drop(lk, lk->sb->rx, n_show);
    emb_rx_consume(lk, 2);
    lk->absorb = end < 0 ? -1 : end - 2;
}

/* Discard the n bytes at rx[0], before a header: the rest of the last dropped frame, or
 * noise (one drop per run, however it is split over reads). */
static void emb_noise(emb_link *lk, uint32_t n)
{
    if (lk->absorb >= 0) {
        if (n <= (uint32_t)lk->absorb) {
            lk->absorb -= (int32_t)n;
        } else {
            emb_drop(lk, lk->sb->rx + lk->absorb, n - (uint32_t)lk->absorb);
            lk->absorb = -1; /* the run of noise goes on up to the next header */
        }
    }
    emb_rx_consume(lk, n);
}

static int emb_wrapped_answers(const emb_want *w, const uint8_t *frame)
{
    const uint8_t *rtu = frame + EMB_WRAP_PREFIX;

    if (rtu[0] != w->slave || ((frame[2] << 8) | frame[3]) != w->address)
        return 0;
    if (rtu[1] == (w->function | 0x80))
        return 1;
    return rtu[1] == w->function && (w->count < 0 || rtu[2] == w->count);
}

/* Frame what rx holds: heartbeats counted, bad frames and noise dropped, valid frames
 * queued as reports, except the first that answers `want` (if given), whose RTU frame
 * goes to rsp: then the reports queued before it are marked (lk->n_before).  Returns
 * that frame's length, 0 if none came. */
static int emb_wrapped_frame(emb_link *lk, const emb_want *want, uint8_t *rsp)
{
    int found = 0, length;
    uint32_t i, keep, end;
    const uint8_t *rtu;
    uint16_t crc;

    while (lk->rx_len > 0) {
        if (lk->hb_len && lk->rx_len >= lk->hb_len &&
            memcmp(lk->sb->rx, lk->hb, lk->hb_len) == 0) {
            emb_rx_consume(lk, lk->hb_len);
            lk->heartbeats++;
            continue;
        }
        for (i = 0; i + 1 < lk->rx_len; i++)
            if (lk->sb->rx[i] == 0xFF && lk->sb->rx[i + 1] == 0xAA)
                break;
        if (i + 1 >= lk->rx_len) { /* no header: keep what may begin one, or a heartbeat */
            keep = lk->sb->rx[lk->rx_len - 1] == 0xFF ? 1 : 0;
            if (emb_hb_partial(lk) > keep)
                keep = emb_hb_partial(lk);
            if (lk->rx_len > keep)
                emb_noise(lk, lk->rx_len - keep);
            break;
        }
        if (i > 0)
            emb_noise(lk, i);
        lk->absorb = 0; /* a header: a new frame begins */
        length = emb_wrapped_rtu_length(lk);
        if (length < 0)
            break;
        if (length == 0 || length > EMB_MAX_RTU) {
            emb_bad(lk, EMB_WRAP_PREFIX + 2, -1); /* not a Modbus reply */
            continue;
        }
        end = EMB_WRAP_PREFIX + (uint32_t)length + 1;
        if (lk->rx_len < end)
            break;
        if (lk->sb->rx[end - 1] != EMB_WRAP_TAIL) {
            emb_bad(lk, end, -1); /* no 0D tail: the length does not add up */
            continue;
        }
        rtu = lk->sb->rx + EMB_WRAP_PREFIX;
        crc = emb_crc16(rtu, length - 2);
        if (rtu[length - 2] != (crc & 0xFF) || rtu[length - 1] != (crc >> 8)) {
            emb_bad(lk, end, (int)end);
            continue;
        }
        if (want && !found && emb_wrapped_answers(want, lk->sb->rx)) {
            memcpy(rsp, rtu, (size_t)length);
            found = length;
            lk->n_before = lk->n_reports;
        } else {
            emb_report_put(lk, lk->sb->rx, end);
        }
        emb_rx_consume(lk, end);
    }
    return found;
}

/* Frame rx with nothing asked: reports, heartbeats, drops (wrapped); heartbeats and
 * stale bytes (plain RTU).  Returns the stale bytes dropped. */
static long emb_stream_idle(emb_link *lk)
{
    if (lk->wrapped) {
        emb_wrapped_frame(lk, NULL, NULL);
        return 0;
    }
    return emb_plain_idle(lk);
}

/* -- the backend functions (csrc/emb_backend.h) ---------------------------------------- */

/* Read what fd holds now into rx without waiting: on a socket one recv(MSG_DONTWAIT)
 * (a DTU's socket is blocking; the link is pumped mostly when poll() said it is
 * readable, and one call then does what a poll and a read did), else a poll and a read
 * (emb_rx_fill).  The bytes read (0: none, or rx is full), or -1 with errno (end of
 * file: emb_eof_errno). */
static int emb_rx_now(emb_link *lk, int fd)
{
    uint32_t space = EMB_RX_SIZE - lk->rx_len;
    ssize_t n;

    if (space == 0)
        return 0;
    do
        n = recv(fd, lk->sb->rx + lk->rx_len, space, MSG_DONTWAIT);
    while (n == -1 && errno == EINTR);
    if (n > 0) {
        lk->rx_len += (uint32_t)n;
        return (int)n;
    }
    if (n == 0) {
        errno = emb_eof_errno(fd);
        return -1;
    }
    if (errno == EAGAIN || errno == EWOULDBLOCK)
        return 0;
    return errno == ENOTSOCK ? emb_rx_fill(lk, fd, 0) : -1;
}

/* Take in and frame what is readable on fd now, without waiting (at most
 * EMB_PUMP_READS reads: a peer that floods the link does not hold the worker; a read
 * that did not fill what rx had free took all there was).  Returns the reports waiting,
 * or -1 with errno. */
static long emb_pump_fd(emb_link *lk, int fd)
{
    int reads, rc;
    uint32_t space;

    for (reads = 0; reads < EMB_PUMP_READS; reads++) {
        space = EMB_RX_SIZE - lk->rx_len;
        rc = emb_rx_now(lk, fd);
        if (rc == -1)
            return -1;
        if (rc == 0)
            break;
        lk->discarded += emb_stream_idle(lk);
        if ((uint32_t)rc < space)
            break;
    }
    return lk->n_reports;
}

/* Before a request: take in what is readable now (reports are queued, heartbeats
 * counted, stale bytes dropped and counted in lk->discarded).  -1 with errno when the
 * link is found closed. */
static int emb_stream_prepare(emb_link *lk, int fd)
{
    if (!emb_has_buffers(lk)) /* every transaction begins here */
        return -1;
    return emb_pump_fd(lk, fd) == -1 ? -1 : 0;
}

/* The deadline for the next bytes: the response deadline until bytes of the frame came
 * in this call (last: when; heartbeats do not count), then the byte timeout from the
 * last ones (byte_ms 0: the whole frame within the response timeout, as libmodbus). */
static int64_t emb_stream_deadline(const emb_link *lk, int64_t response, int64_t last,
                                   int byte_ms)
{
    if (lk->rx_len == 0 || last == 0 || byte_ms <= 0)
        return response;
    return last + (int64_t)byte_ms * 1000000;
}

/* Plain RTU stream with the echo option: the request's own bytes come back first. */
static int emb_stream_skip_echo(emb_link *lk, int fd, const uint8_t *sent, int sent_len,
                                int first_ms, int byte_ms)
{
    int64_t response = emb_now_ns() + (int64_t)first_ms * 1000000, last = 0;
    int rc;

    for (;;) {
        emb_hb_strip(lk);
        if (lk->rx_len >= (uint32_t)sent_len) {
            rc = memcmp(lk->sb->rx, sent, (size_t)sent_len);
            emb_rx_consume(lk, (uint32_t)sent_len);
            lk->discarded += sent_len;
            if (rc != 0) {
                errno = EMB_EECHO;
                return -1;
            }
            return 0;
        }
        rc = emb_rx_fill(lk, fd, emb_stream_deadline(lk, response, last, byte_ms));
        if (rc == -1)
            return -1;
        if (rc == 0) {
            errno = lk->rx_len ? EMB_EPARTIAL : ETIMEDOUT;
            return -1;
        }
        last = emb_now_ns();
    }
}

/* Take in what is readable on fd now into the link's receive buffer, without waiting
 * or framing (the loop engine, csrc/emb_loop.c, on a readable socket; then
 * emb_stream_try).  The bytes read (0: none, or the buffer is full), or -1 with errno
 * (end of file: emb_eof_errno). */
int emb_stream_fill(emb_link *lk, int fd)
{
    if (!emb_has_buffers(lk))
        return -1;
    return emb_rx_fill(lk, fd, 0);
}

/* Plain RTU stream: frame one reply for slave from the bytes received (lk->sb->rx),
 * heartbeats before it skipped, without reading or waiting (the blocking receive below
 * and the loop engine, csrc/emb_loop.c, frame with it).  Returns the frame's length in
 * rsp (EMB_MAX_ADU bytes) with its CRC checked, 0 for another slave's frame, -1 with
 * errno (EMBBADDATA: bytes that begin no reply, left in rx for the drain; EMBBADCRC), or
 * EMB_STREAM_MORE: no whole frame yet (nothing taken).  *got: the bytes taken. */
int emb_stream_try(emb_link *lk, int slave, uint8_t *rsp, int *got)
{
    int need, have;
    uint16_t crc;

    *got = 0;
    if (emb_hb_strip(lk) || lk->rx_len == 0)
        return EMB_STREAM_MORE;
    have = lk->rx_len < EMB_MAX_RTU ? (int)lk->rx_len : EMB_MAX_RTU;
    need = emb_reply_length(lk->sb->rx, have, 0);
    if (need >= 0 && have < need)
        return EMB_STREAM_MORE;
    if (need > 0)
        have = need;
    memcpy(rsp, lk->sb->rx, (size_t)have);
    *got = have;
    if (need < 0) { /* the bytes stay: the drain takes them */
        errno = EMBBADDATA;
        return -1;
    }
    emb_rx_consume(lk, (uint32_t)have);
    if (rsp[0] != slave && rsp[0] != 0) /* as on plain RTU: another slave's frame */
        return 0;
    crc = emb_crc16(rsp, need - 2);
    if (rsp[need - 2] != (crc & 0xFF) || rsp[need - 1] != (crc >> 8)) {
        errno = EMBBADCRC;
        return -1;
    }
    return need;
}

/* Plain RTU stream: receive one reply frame into rsp, heartbeats skipped before it; the
 * contract of emb_backend.recv.  Bytes behind the frame stay in rx. */
static int emb_stream_recv(emb_link *lk, int fd, const emb_want *want, int first_ms,
                           int byte_ms, uint8_t *rsp, int *got)
{
    int64_t response = emb_now_ns() + (int64_t)first_ms * 1000000, last = 0;
    int have, rc;

    for (;;) {
        rc = emb_stream_try(lk, want->slave, rsp, got);
        if (rc != EMB_STREAM_MORE)
            return rc;
        rc = emb_rx_fill(lk, fd, emb_stream_deadline(lk, response, last, byte_ms));
        if (rc == -1)
            return -1;
        if (rc == 0) {
            have = lk->rx_len < EMB_MAX_RTU ? (int)lk->rx_len : EMB_MAX_RTU;
            memcpy(rsp, lk->sb->rx, (size_t)have);
            *got = have;
            errno = lk->rx_len ? EMB_EPARTIAL : ETIMEDOUT;
            return -1;
        }
        last = emb_now_ns();
    }
}

/* Plain RTU stream: bytes received and not framed yet, heartbeats aside. */
static int emb_stream_pending(emb_link *lk, int fd)
{
    emb_hb_strip(lk);
    return (int)lk->rx_len + emb_pending(fd);
}

/* Wrapped: wait up to first_ms for the frame that answers the request (want: slave,
 * function, register address, and for a read the byte count; -1 for a write), queueing
 * every other frame as a report, also one of our slave, function and address with
 * another count (the MCU reporting a range that starts where we read).  The frames
 * behind the reply are queued too.  Returns the reply's RTU frame length in rsp, or -1
 * with errno: ETIMEDOUT (no reply, also when a frame stopped short: a late wrapped frame
 * is still a valid report), or the link's errno. */
static int emb_wrapped_recv(emb_link *lk, int fd, const emb_want *want, int first_ms,
                            int byte_ms, uint8_t *rsp, int *got)
{
    int64_t deadline = emb_now_ns() + (int64_t)first_ms * 1000000;
    int len, rc;

    (void)byte_ms;
    *got = 0;
    for (;;) {
        len = emb_wrapped_frame(lk, want, rsp);
        if (len > 0) {
            *got = len;
            return len;
        }
        rc = emb_rx_fill(lk, fd, deadline);
        if (rc == -1)
            return -1;
        if (rc == 0) {
            errno = ETIMEDOUT;
            return -1;
        }
    }
}

/* Wrapped (an edge MCU): FF AA | the request's register address | the RTU frame | 0D
 * (sent holds the RTU frame). */
static int emb_wrapped_send(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu,
                            int pdu_len, uint8_t *sent, int *sent_len)
{
    uint8_t wrapped[EMB_WRAPPED_REQ_MAX];

    (void)lk;
    if (emb_rtu_frame(slave, pdu, pdu_len, sent, sent_len) == -1)
        return -1;
    if (pdu_len < 3) { /* no register address to wrap it with */
        errno = EINVAL;
        return -1;
    }
    wrapped[0] = 0xFF;
    wrapped[1] = 0xAA;
    wrapped[2] = pdu[1];
    wrapped[3] = pdu[2];
    memcpy(wrapped + 4, sent, (size_t)*sent_len);
    wrapped[4 + *sent_len] = EMB_WRAP_TAIL;
    return emb_write_all(modbus_get_socket(ctx), wrapped, *sent_len + 5);
}

/* When a settle or drain that began at start_ns ends (emb_discard_input's timing): at
 * total_ms, or quiet_ms after the last bytes (last_ns, 0: none yet) if that is later, but
 * never past limit_ms (at least total_ms).  Pure: the blocking discard below waits for
 * it, the loop engine (csrc/emb_loop.c) sets it as the settling link's deadline. */
int64_t emb_settle_until(int64_t start_ns, int64_t last_ns, int total_ms, int quiet_ms,
                         int limit_ms)
{
    int64_t total = start_ns + (int64_t)total_ms * 1000000, until = total;

    if (limit_ms < total_ms)
        limit_ms = total_ms;
    if (last_ns) {
        until = last_ns + (int64_t)quiet_ms * 1000000;
        if (until < total)
            until = total;
    }
    if (until > start_ns + (int64_t)limit_ms * 1000000)
        until = start_ns + (int64_t)limit_ms * 1000000;
    return until;
}

/* Frame what the link received with nothing asked (a settling link's bytes, input on
 * an idle one): wrapped reports queued, heartbeats counted, stale bytes dropped.  The
 * bytes dropped, or -1 with errno EINVAL for a link without stream buffers. */
long emb_stream_take_idle(emb_link *lk)
{
    if (!emb_has_buffers(lk))
        return -1;
    return emb_stream_idle(lk);
}

/* emb_discard_input for a stream link: what comes is framed (reports queued: a late
 * wrapped frame carries its address, so it is a valid report; heartbeats counted) and
 * the rest dropped.  Returns the stale bytes dropped (plain RTU streams). */
static long emb_stream_discard(emb_link *lk, int fd, int total_ms, int quiet_ms,
                               int limit_ms)
{
    int64_t start = emb_now_ns(), last = 0;
    long dropped = 0;
    int rc;

    for (;;) {
        rc = emb_rx_fill(lk, fd, emb_settle_until(start, last, total_ms, quiet_ms, limit_ms));
        if (rc == -1)
            return -1;
        if (rc == 0)
            return dropped;
        dropped += emb_stream_idle(lk);
        last = emb_now_ns();
    }
}

/* Idle: read what is readable now, without waiting, and frame it (reports queued,
 * heartbeats counted). */
static long emb_stream_pump(emb_link *lk, int fd)
{
    if (!emb_has_buffers(lk))
        return -1;
    return emb_pump_fd(lk, fd);
}

/* Bytes that came before the link, framed as if received now, nothing asked. */
static long emb_stream_feed(emb_link *lk, const uint8_t *data, int n)
{
    uint32_t take;

    if (!emb_has_buffers(lk))
        return -1;
    do { /* also with no bytes: what rx holds is framed again, as on any read */
        take = EMB_RX_SIZE - lk->rx_len;
        if (take > (uint32_t)n)
            take = (uint32_t)n;
        if (take)
            memcpy(lk->sb->rx + lk->rx_len, data, take);
        lk->rx_len += take;
        data += take;
        n -= (int)take;
        lk->discarded += emb_stream_idle(lk);
    } while (n > 0);
    return lk->n_reports;
}

static long emb_stream_settle(emb_link *lk, int fd, int total_ms, int quiet_ms, int limit_ms)
{
    return emb_has_buffers(lk) ? emb_stream_discard(lk, fd, total_ms, quiet_ms, limit_ms) : -1;
}

const emb_backend emb_stream_backend = {
    "stream", 1, 2, 5, emb_stream_prepare, emb_rtu_send, emb_stream_skip_echo,
    emb_stream_recv, NULL, emb_stream_pending, emb_stream_settle, emb_stream_pump,
    emb_stream_feed,
};

/* Wrapped: the first answer is taken (the frames behind it are reports), no echo. */
const emb_backend emb_wrapped_backend = {
    "wrapped", 1, 2, 0, emb_stream_prepare, emb_wrapped_send, NULL, emb_wrapped_recv, NULL,
    emb_stream_pending, emb_stream_settle, emb_stream_pump, emb_stream_feed,
};
