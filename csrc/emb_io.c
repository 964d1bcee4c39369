/* edgemodbus: transaction helpers around libmodbus 3.1.6.
 *
 * Each function does a whole step (drop stale input, send, skip an echo, receive, check)
 * so that the Python bus worker makes one C call, with the GIL released, per Modbus
 * transaction.  libmodbus keeps the line set-up (serial port, termios, RS-485 and RTS)
 * and sends RTU requests; we receive: poll(), not libmodbus's select(), whose FD_SET
 * overflows for an fd of 1024 and more; the length from the function code and byte count,
 * the response and byte timeouts, the CRC (emb_recv_frame).  The checks that tie a reply
 * to its request are ours too, because 3.1.6 does not make them all: it loses undefined
 * exception codes, ignores the MBAP unit id and length, accepts a protocol id with one
 * zero byte, and sends raw requests with transaction id 0.  On DTU streams (heartbeats,
 * wrapped report frames) the receiving is csrc/emb_stream.c's.  No globals, no
 * allocation: callers own every buffer. */
#include "emb_wire.h"

#include <errno.h>
#include <poll.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#define EMB_WRAPPED_REQ_MAX (4 + EMB_MAX_RTU + 1) /* FF AA, address, RTU frame, 0D */

/* CRC-16/MODBUS, polynomial 0xA001 reflected, initial 0xFFFF (Modbus over Serial Line
 * v1.02, 6.2.2); sent low byte first. */
uint16_t emb_crc16(const uint8_t *p, int n)
{
    uint16_t crc = 0xFFFF;
    int i, bit;

    for (i = 0; i < n; i++) {
        crc ^= p[i];
        for (bit = 0; bit < 8; bit++)
            crc = (crc & 1) ? (uint16_t)((crc >> 1) ^ 0xA001) : (uint16_t)(crc >> 1);
    }
    return crc;
}

/* CLOCK_MONOTONIC in nanoseconds (the reader's and the stream framing's clock). */
int64_t emb_clock_ns(void)
{
    struct timespec now;

    clock_gettime(CLOCK_MONOTONIC, &now);
    return (int64_t)now.tv_sec * 1000000000 + now.tv_nsec;
}

static long emb_elapsed_ms(const struct timespec *since)
{
    struct timespec now;

    clock_gettime(CLOCK_MONOTONIC, &now);
    return (long)(now.tv_sec - since->tv_sec) * 1000L +
           (long)(now.tv_nsec - since->tv_nsec) / 1000000L;
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

/* Wait until fd is readable (or reports a hangup or an error, which the next read
 * returns) for up to ms: 1 readable, 0 timed out, -1 with errno.  poll(), not select():
 * fds of 1024 and more are safe here. */
static int emb_wait_readable(int fd, int ms)
{
    struct pollfd pfd;
    struct timespec start;
    long left;
    int rc;

    clock_gettime(CLOCK_MONOTONIC, &start);
    pfd.fd = fd;
    for (;;) {
        left = ms - emb_elapsed_ms(&start);
        pfd.events = POLLIN;
        pfd.revents = 0;
        rc = poll(&pfd, 1, left > 0 ? (int)left : 0);
        if (rc == -1) {
            if (errno == EINTR)
                continue;
            return -1;
        }
        if (rc == 0)
            return 0;
        if (pfd.revents & POLLNVAL) {
            errno = EBADF;
            return -1;
        }
        return 1;
    }
}

/* Sleep until the monotonic clock reaches t_ns. */
static void emb_sleep_until(int64_t t_ns)
{
    struct timespec ts;

    ts.tv_sec = (time_t)(t_ns / 1000000000);
    ts.tv_nsec = (long)(t_ns % 1000000000);
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR)
        ;
}

/* When the next bytes of a frame must have come, and whether we slept for them. */
typedef struct {
    int64_t deadline; /* monotonic ns */
    int slept_for;    /* bytes the last sleep waited for, 0 if it did not sleep */
} emb_pacer;

static void emb_pacer_start(emb_pacer *p, int first_ms)
{
    p->deadline = emb_clock_ns() + (int64_t)first_ms * 1000000;
    p->slept_for = 0;
}

/* After a read that returned n bytes of a frame of which `left` are still to come: on
 * sockets, the byte timeout counts from now (byte_ms 0: the deadline stays, the whole
 * frame within the response timeout, as libmodbus).  On a serial line (lk->char_ns) the
 * rest of the frame is on the wire at one character time per byte (Modbus over Serial
 * Line v1.02, 2.5.1.1: no gap over 1.5 characters inside a frame), so sleep until it
 * should all be here, half a character early, and read it in one go, instead of a poll()
 * and a read() per byte; the byte timeout then counts from that expected arrival.  When
 * a sleep brought fewer bytes than it waited for, the frame is late or stopped short:
 * the byte timeout counts from now, without sleeping, until bytes come again. */
static void emb_pace(const emb_link *lk, emb_pacer *p, int n, int left, int byte_ms)
{
    int64_t expected = emb_clock_ns();

    if (lk->char_ns > 0 && left > 1 && !(p->slept_for && n < p->slept_for)) {
        expected += (int64_t)left * lk->char_ns;
        emb_sleep_until(expected - lk->char_ns / 2);
        p->slept_for = left;
    } else {
        p->slept_for = 0;
    }
    if (byte_ms > 0)
        p->deadline = expected + (int64_t)byte_ms * 1000000;
}

/* Wait until fd is readable or the monotonic clock passes deadline_ns: 1, 0, -1. */
int emb_wait_until(int fd, int64_t deadline_ns)
{
    int64_t left = deadline_ns - emb_clock_ns();

    return emb_wait_readable(fd, left > 0 ? (int)((left + 999999) / 1000000) : 0);
}

/* The errno for end-of-file on fd: the peer closed the connection (ECONNRESET) on a
 * socket; on a serial device, a tty that hung up (a USB adapter unplugged, a pty whose
 * master side closed) reads EOF where writes fail with EIO: report EIO there too. */
int emb_eof_errno(int fd)
{
    struct stat st;

    if (fstat(fd, &st) == 0 && !S_ISSOCK(st.st_mode))
        return EIO;
    return ECONNRESET;
}

/* Bytes already received on fd and not read yet (0 if the driver cannot tell). */
int emb_pending(int fd)
{
    int n = 0;

    if (ioctl(fd, FIONREAD, &n) == -1)
        return 0;
    return n;
}

/* Discard input on fd.  RTU frames carry no transaction id, so a reply that comes
 * after the response timeout would be taken as the answer to the next request.
 * Waits up to total_ms for stray bytes; once bytes come, goes on until quiet_ms pass
 * without a new one (a late reply still arriving as total_ms runs out is taken whole),
 * but never past limit_ms (a line that never falls quiet).  total_ms = 0 and
 * limit_ms = 0 only take what is already there.
 * Returns the number of bytes discarded, or -1 with errno set (ECONNRESET when the
 * peer closed the connection, EIO when a serial device went away). */
long emb_discard_input(int fd, int total_ms, int quiet_ms, int limit_ms)
{
    uint8_t sink[512];
    struct timespec start;
    long discarded = 0;
    long waited;
    long timeout;
    int rc;
    ssize_t n;

    if (limit_ms < total_ms)
        limit_ms = total_ms;
    clock_gettime(CLOCK_MONOTONIC, &start);
    for (;;) {
        waited = emb_elapsed_ms(&start);
        if (discarded == 0) {
            timeout = total_ms - waited;
        } else {
            timeout = limit_ms - waited;
            if (quiet_ms < timeout)
                timeout = quiet_ms;
        }
        rc = emb_wait_readable(fd, timeout > 0 ? (int)timeout : 0);
        if (rc == -1)
            return -1;
        if (rc == 0)
            return discarded;
        n = read(fd, sink, sizeof(sink));
        if (n == 0) {
            errno = emb_eof_errno(fd);
            return -1;
        }
        if (n < 0) {
            if (errno == EINTR || errno == EAGAIN)
                continue;
            return -1;
        }
        discarded += n;
    }
}

/* Drop whatever input is already pending (a reply we gave up on, noise, an answer to
 * a broadcast) so that it cannot be taken as the answer to the request we send next:
 * RTU frames carry no transaction id (Modbus over Serial Line v1.02, 2.5.1).  A link
 * found closed here fails the request before anything is sent. */
static int emb_drop_pending(emb_link *lk, int fd)
{
    long n;

    if (emb_is_stream(lk)) /* reports are kept, heartbeats counted */
        return emb_stream_drop_pending(lk, fd);
    n = emb_discard_input(fd, 0, 0, 0);
    if (n == -1)
        return -1;
    lk->discarded += n;
    return 0;
}

static int emb_write_all(int fd, const uint8_t *p, int n)
{
    ssize_t w;

    while (n > 0) {
        w = send(fd, p, (size_t)n, MSG_NOSIGNAL);
        if (w == -1) {
            if (errno == EINTR)
                continue;
            return -1;
        }
        p += w;
        n -= (int)w;
    }
    return 0;
}

/* Send pdu (function code first) to slave; the ADU put on the wire goes to sent.
 * Modbus TCP: we build the MBAP header ourselves with the next transaction id
 * (libmodbus 3.1.6 sends raw requests with id 0, which would match any stale reply).
 * RTU: libmodbus adds the CRC and drives RTS on serial lines.  Wrapped (an edge MCU):
 * FF AA | the request's register address | the RTU frame | 0D (sent holds the RTU
 * frame). */
static int emb_send_adu(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu,
                        int pdu_len, uint8_t *sent, int *sent_len)
{
    uint8_t wrapped[EMB_WRAPPED_REQ_MAX];
    uint16_t crc;

    if (pdu_len < 1 || pdu_len > EMB_MAX_ADU - EMB_MBAP || slave < 0 || slave > 255) {
        errno = EINVAL;
        return -1;
    }
    if (lk->mbap) {
        lk->tid = (lk->tid + 1U) & 0xFFFFU;
        sent[0] = (uint8_t)(lk->tid >> 8);
        sent[1] = (uint8_t)(lk->tid & 0xFF);
        sent[2] = 0;
        sent[3] = 0;
        sent[4] = (uint8_t)((pdu_len + 1) >> 8);
        sent[5] = (uint8_t)((pdu_len + 1) & 0xFF);
        sent[6] = (uint8_t)slave;
        memcpy(sent + EMB_MBAP, pdu, (size_t)pdu_len);
        *sent_len = EMB_MBAP + pdu_len;
        return emb_write_all(modbus_get_socket(ctx), sent, *sent_len);
    }
    if (pdu_len > 253) { /* RTU ADU: address + PDU + CRC <= 256 bytes (Serial Line 2.5.1) */
        errno = EINVAL;
        return -1;
    }
    sent[0] = (uint8_t)slave;
    memcpy(sent + 1, pdu, (size_t)pdu_len);
    crc = emb_crc16(sent, pdu_len + 1);
    sent[pdu_len + 1] = (uint8_t)(crc & 0xFF);
    sent[pdu_len + 2] = (uint8_t)(crc >> 8);
    *sent_len = pdu_len + 3;
    if (lk->wrapped) {
        if (pdu_len < 3) { /* no register address to wrap it with */
            errno = EINVAL;
            return -1;
        }
        wrapped[0] = 0xFF;
        wrapped[1] = 0xAA;
        wrapped[2] = pdu[1];
        wrapped[3] = pdu[2];
        memcpy(wrapped + 4, sent, (size_t)*sent_len);
        wrapped[4 + *sent_len] = 0x0D;
        return emb_write_all(modbus_get_socket(ctx), wrapped, *sent_len + 5);
    }
    if (modbus_set_slave(ctx, slave) == -1)
        return -1;
    return modbus_send_raw_request(ctx, sent, pdu_len + 1) == -1 ? -1 : 0;
}

/* With the echo option: read back exactly the request's own bytes, which a 2-wire
 * adapter without echo suppression puts on our receive line, before the reply. */
static int emb_skip_echo(modbus_t *ctx, emb_link *lk, const uint8_t *sent, int sent_len)
{
    uint8_t echo[EMB_MAX_ADU];
    int fd = modbus_get_socket(ctx);
    int byte_ms = emb_timeout_ms(ctx, 1);
    int got = 0;
    int rc;
    ssize_t n;
    emb_pacer pace;

    if (emb_is_stream(lk))
        return emb_stream_skip_echo(lk, fd, sent, sent_len, emb_timeout_ms(ctx, 0), byte_ms);
    emb_pacer_start(&pace, emb_timeout_ms(ctx, 0));
    while (got < sent_len) {
        rc = emb_wait_until(fd, pace.deadline);
        if (rc == -1)
            return -1;
        if (rc == 0) {
            errno = got ? EMB_EPARTIAL : ETIMEDOUT;
            return -1;
        }
        n = read(fd, echo + got, (size_t)(sent_len - got));
        if (n == 0) {
            errno = emb_eof_errno(fd);
            return -1;
        }
        if (n < 0) {
            if (errno == EINTR || errno == EAGAIN)
                continue;
            return -1;
        }
        got += (int)n;
        if (got < sent_len)
            emb_pace(lk, &pace, (int)n, sent_len - got, byte_ms);
    }
    lk->discarded += got;
    if (memcmp(echo, sent, (size_t)sent_len) != 0) {
        errno = EMB_EECHO;
        return -1;
    }
    return 0;
}

/* Length of the reply ADU whose first `got` bytes are in p, as its header tells it
 * (Modbus Application Protocol v1.1b3, ch. 6: a read reply carries a byte count,
 * 6.1-6.4; a write reply echoes a fixed-size part of the request, 6.5, 6.6, 6.11, 6.12,
 * 6.16; an exception reply is function | 0x80 and one code, ch. 7); while fewer than
 * header + 2 bytes came: that many (every reply has them), so a read of what this
 * returns never goes past the frame's end.  -1: the byte count does not fit in an ADU
 * (libmodbus's EMBBADDATA).  Function codes of unknown length are framed as libmodbus
 * frames them (the function and one byte), on Modbus TCP by the MBAP length when it is
 * plausible (Modbus Messaging on TCP/IP v1.0b, 3.1.3). */
int emb_reply_length(const uint8_t *p, int got, int mbap)
{
    int h = mbap ? EMB_MBAP : 1;
    int crc = mbap ? 0 : 2;
    int max = mbap ? EMB_MAX_ADU : EMB_MAX_RTU;
    int fc, n, mlen;

    if (got < h + 2)
        return h + 2 + crc;
    fc = p[h];
    if (fc & 0x80) {
        n = h + 2 + crc;
    } else {
        switch (fc) {
        case 0x01: case 0x02: case 0x03: case 0x04:
        case 0x11: case 0x17: /* report server id, read/write registers: byte count too */
            n = h + 2 + p[h + 1] + crc;
            break;
        case 0x05: case 0x06: case 0x0F: case 0x10:
            n = h + 5 + crc;
            break;
        case 0x16:
            n = h + 7 + crc;
            break;
        default:
            n = h + 2 + crc;
            if (mbap) {
                mlen = (p[4] << 8) | p[5];
                if (6 + mlen > n && 6 + mlen <= max)
                    n = 6 + mlen;
            }
        }
    }
    return n > max ? -1 : n;
}

/* Receive one reply frame into rsp (at least EMB_MAX_ADU bytes) with poll() and read(),
 * reading exactly what the frame still needs (emb_reply_length), never a byte past its
 * end: what follows stays in the fd (another frame that emb_exchange looks at, or stale
 * input that the next request drops).  first_ms: the wait for the first byte; then the
 * ctx's byte timeout between bytes (0: the whole frame within first_ms, as libmodbus),
 * on a serial line counted from when the bytes should have come (emb_pace).
 * Returns the frame length; 0 for an RTU frame from another slave than `slave` (its CRC
 * not checked: libmodbus does the same); -1 with errno: ETIMEDOUT (nothing came),
 * EMB_EPARTIAL (the frame stopped short), EMBBADDATA (a byte count too large for an ADU),
 * EMBBADCRC, the emb_eof_errno at end of file, or the read's errno.  *got: bytes read. */
static int emb_recv_frame(modbus_t *ctx, emb_link *lk, int slave, int first_ms,
                          uint8_t *rsp, int *got)
{
    int fd = modbus_get_socket(ctx);
    int byte_ms = emb_timeout_ms(ctx, 1);
    int need = emb_reply_length(rsp, 0, lk->mbap);
    int n_got = 0;
    int rc;
    ssize_t n;
    uint16_t crc;
    emb_pacer pace;

    if (emb_is_stream(lk)) /* heartbeats between the request and the reply */
        return emb_stream_recv_frame(lk, fd, slave, first_ms, byte_ms, rsp, got);
    *got = 0;
    emb_pacer_start(&pace, first_ms);
    for (;;) {
        rc = emb_wait_until(fd, pace.deadline);
        if (rc == -1)
            return -1;
        if (rc == 0) {
            errno = n_got ? EMB_EPARTIAL : ETIMEDOUT;
            return -1;
        }
        n = read(fd, rsp + n_got, (size_t)(need - n_got));
        if (n == 0) {
            errno = emb_eof_errno(fd);
            return -1;
        }
        if (n < 0) {
            if (errno == EINTR || errno == EAGAIN)
                continue;
            return -1;
        }
        n_got += (int)n;
        *got = n_got;
        need = emb_reply_length(rsp, n_got, lk->mbap);
        if (need < 0) {
            errno = EMBBADDATA;
            return -1;
        }
        if (n_got >= need)
            break;
        emb_pace(lk, &pace, (int)n, need - n_got, byte_ms);
    }
    if (lk->mbap)
        return n_got;
    if (rsp[0] != slave && rsp[0] != 0) /* 0: a broadcast address is checked, as libmodbus */
        return 0;
    crc = emb_crc16(rsp, n_got - 2);
    if (rsp[n_got - 2] != (crc & 0xFF) || rsp[n_got - 1] != (crc >> 8)) {
        errno = EMBBADCRC;
        return -1;
    }
    return n_got;
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

/* 0 if rsp (len bytes) answers pdu sent to slave: a normal reply (*exc = -1) or an
 * exception response to the request's function (*exc = its code, any of 0..255:
 * Modbus Application Protocol v1.1b3, 7); else the EMB_E* errno saying why not.
 * count: the byte count a read reply must carry (6.1-6.4), or -1 (writes: the caller
 * checks their echo). */
static int emb_check(const emb_link *lk, int slave, const uint8_t *pdu, int count,
                     const uint8_t *rsp, int len, int *exc)
{
    int h = lk->mbap ? EMB_MBAP : 1;
    int fc;

    *exc = -1;
    if (len < h + 2)
        return EMB_ECOUNT;
    if (lk->mbap) {
        if ((unsigned)((rsp[0] << 8) | rsp[1]) != lk->tid)
            return EMB_ETID;
        if (rsp[2] != 0 || rsp[3] != 0)
            return EMB_EPROTOID;
        if (((rsp[4] << 8) | rsp[5]) != len - 6)
            return EMB_EMBAPLEN;
    }
    if (rsp[h - 1] != slave)
        return EMB_ESLAVE;
    fc = rsp[h];
    if (fc == (pdu[0] | 0x80)) {
        *exc = rsp[h + 1];
        return 0;
    }
    if (fc & 0x80)
        return EMB_EOTHEREXC;
    if (fc != pdu[0])
        return EMB_EFUNCTION;
    if (count >= 0 && rsp[h + 1] != count)
        return EMB_ECOUNT;
    return 0;
}

/* Did what came back (got bytes) start with our own request? */
static int emb_looks_like_echo(const uint8_t *rsp, int got, const uint8_t *sent, int sent_len)
{
    int i = 0;

    while (i < sent_len && i < got && rsp[i] == sent[i])
        i++;
    return i >= 5 || (i == sent_len && i > 0);
}

/* The reply to a wrapped request already sent: the first wrapped frame that answers it
 * (csrc/emb_stream.c queues the others as reports), its RTU frame checked as any
 * reply's.  No "last answer wins": frames behind the reply are reports. */
static int emb_exchange_wrapped(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu,
                                int count, uint8_t *rsp)
{
    int len, err, exc;

    len = emb_stream_recv_wrapped(lk, modbus_get_socket(ctx), slave, pdu, count,
                                  emb_timeout_ms(ctx, 0), rsp);
    if (len == -1)
        return -1;
    lk->rsp_len = len;
    err = emb_check(lk, slave, pdu, count, rsp, len, &exc);
    return emb_checked(err, exc, len);
}

/* One request and its checked reply (see emb_check); returns the reply ADU length
 * with the ADU in rsp, or -1 with errno (EMB_EEXCEPTION + code for an exception). */
static int emb_exchange(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu,
                        int pdu_len, int count, uint8_t *rsp)
{
    uint8_t sent[EMB_MAX_ADU];
    uint8_t next[EMB_MAX_ADU];
    int fd = modbus_get_socket(ctx);
    int rtu = !lk->mbap;
    struct timespec start;
    int sent_len = 0;
    int len, len2, err, err2, exc, exc2, got, got2, wait, skipped = 0;

    lk->rsp_len = 0;
    if (emb_drop_pending(lk, fd) == -1)
        return -1;
    if (emb_send_adu(ctx, lk, slave, pdu, pdu_len, sent, &sent_len) == -1)
        return -1;
    if (lk->wrapped)
        return emb_exchange_wrapped(ctx, lk, slave, pdu, count, rsp);
    if (rtu && lk->echo && emb_skip_echo(ctx, lk, sent, sent_len) == -1)
        return -1;
    wait = emb_timeout_ms(ctx, 0); /* for the first byte: the response timeout */
    clock_gettime(CLOCK_MONOTONIC, &start);
    for (;;) {
        len = emb_recv_frame(ctx, lk, slave, wait, rsp, &got);
        if (len <= 0) {
            err = len == 0 ? EMB_ESLAVE : errno;
            if (err == ETIMEDOUT && skipped)
                err = EMB_ETID; /* only replies to other requests came */
            if (rtu && !lk->echo && err != ETIMEDOUT &&
                emb_looks_like_echo(rsp, got, sent, sent_len))
                err = EMB_EECHOSEEN;
            errno = err;
            return -1;
        }
        err = emb_check(lk, slave, pdu, count, rsp, len, &exc);
        if (err != EMB_ETID)
            break;
        /* Modbus TCP: a reply to an earlier request (its transaction id says so) is
         * skipped and ours is awaited for the rest of the response timeout. */
        lk->discarded += len;
        skipped++;
        wait = emb_timeout_ms(ctx, 0) - (int)emb_elapsed_ms(&start);
        if (wait <= 0) {
            errno = EMB_ETID;
            return -1;
        }
    }
    /* Another whole frame right behind this one (a DTU that held a late reply and sends
     * it with the next one, or repeats a reply): the last answer to this request wins,
     * so a stale reply to an earlier request is never taken for this one. */
    if ((emb_is_stream(lk) ? emb_stream_pending(lk, fd) : emb_pending(fd)) >=
        (rtu ? 5 : EMB_MBAP + 2)) {
        len2 = emb_recv_frame(ctx, lk, slave, 0, next, &got2);
        if (len2 > 0) {
            err2 = emb_check(lk, slave, pdu, count, next, len2, &exc2);
            if (err2 == 0) {
                lk->discarded += len;
                memcpy(rsp, next, (size_t)len2);
                len = len2;
                err = 0;
                exc = exc2;
            } else {
                lk->discarded += len2;
            }
        } else {
            lk->discarded += got2; /* another slave's frame, or a bad one */
        }
    }
    lk->rsp_len = len; /* also when rejected: the caller may show why */
    if (err && rtu && !lk->echo && emb_looks_like_echo(rsp, len, sent, sent_len))
        err = EMB_EECHOSEEN;
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
    data = rsp + (lk->mbap ? EMB_MBAP : 1) + 2;
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
 * rsp (at least 260 bytes): header checked (slave or MBAP), function code checked,
 * exception responses returned as errors.  The caller checks the rest (a write's echo).
 * Returns the ADU length, or -1 with errno. */
int emb_transact(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                 uint8_t *rsp)
{
    return emb_exchange(ctx, lk, slave, pdu, pdu_len, -1, rsp);
}

/* Send without waiting for a reply: broadcast (slave 0) requests get none
 * (Modbus over Serial Line v1.02, 2.1).  An echo is still read back. */
int emb_send(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len)
{
    uint8_t sent[EMB_MAX_ADU];
    int sent_len = 0;

    lk->rsp_len = 0;
    if (emb_drop_pending(lk, modbus_get_socket(ctx)) == -1)
        return -1;
    if (emb_send_adu(ctx, lk, slave, pdu, pdu_len, sent, &sent_len) == -1)
        return -1;
    if (!lk->mbap && !lk->wrapped && lk->echo && emb_skip_echo(ctx, lk, sent, sent_len) == -1)
        return -1;
    return 0;
}
