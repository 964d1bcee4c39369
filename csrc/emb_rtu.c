/* edgemodbus: plain RTU and Modbus TCP links (see emb_backend.h).
 *
 * libmodbus keeps the line set-up (serial port, termios, RS-485 and RTS) and sends RTU
 * requests; we receive: poll(), not libmodbus's select(), whose FD_SET overflows for an
 * fd of 1024 and more; the length from the function code and byte count
 * (emb_reply_length), the response and byte timeouts, the CRC.  On Modbus TCP we frame
 * the request ourselves (libmodbus 3.1.6 sends raw requests with transaction id 0, which
 * would match any stale reply) and check the MBAP header of the reply (3.1.6 ignores its
 * length and accepts a protocol id with one zero byte).  No globals, no allocation. */
#include "emb_rtu.h"

#include <errno.h>
#include <string.h>
#include <unistd.h>

#include "emb_check.h"
#include "emb_util.h"

/* When the next bytes of a frame must have come, and whether we slept for them. */
typedef struct {
    int64_t deadline; /* monotonic ns */
    int slept_for;    /* bytes the last sleep waited for, 0 if it did not sleep */
} emb_pacer;

static void emb_pacer_start(emb_pacer *p, int first_ms)
{
    p->deadline = emb_now_ns() + (int64_t)first_ms * 1000000;
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
    int64_t expected = emb_now_ns();

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

/* The RTU frame of pdu for slave into sent: address, PDU, CRC (Modbus over Serial Line
 * 2.5.1: at most 256 bytes).  0, or -1 with EINVAL. */
int emb_rtu_frame(int slave, const uint8_t *pdu, int pdu_len, uint8_t *sent, int *sent_len)
{
    uint16_t crc;

    if (pdu_len > 253) {
        errno = EINVAL;
        return -1;
    }
    sent[0] = (uint8_t)slave;
    memcpy(sent + 1, pdu, (size_t)pdu_len);
    crc = emb_crc16(sent, pdu_len + 1);
    sent[pdu_len + 1] = (uint8_t)(crc & 0xFF);
    sent[pdu_len + 2] = (uint8_t)(crc >> 8);
    *sent_len = pdu_len + 3;
    return 0;
}

/* RTU: libmodbus adds the CRC again and drives RTS on serial lines. */
int emb_rtu_send(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                 uint8_t *sent, int *sent_len)
{
    if (emb_rtu_frame(slave, pdu, pdu_len, sent, sent_len) == -1)
        return -1;
    if (modbus_set_slave(ctx, slave) == -1)
        return -1;
    lk->syscalls++; /* one write(2) in libmodbus, with no RTS line to drive */
    return modbus_send_raw_request(ctx, sent, pdu_len + 1) == -1 ? -1 : 0;
}

/* Modbus TCP: our MBAP header with the next transaction id. */
static int emb_mbap_send(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu,
                         int pdu_len, uint8_t *sent, int *sent_len)
{
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
    lk->syscalls++;
    return emb_write_all(modbus_get_socket(ctx), sent, *sent_len);
}

/* With the echo option: read back exactly the request's own bytes, which a 2-wire
 * adapter without echo suppression puts on our receive line, before the reply. */
static int emb_rtu_skip_echo(emb_link *lk, int fd, const uint8_t *sent, int sent_len,
                             int first_ms, int byte_ms)
{
    uint8_t echo[EMB_MAX_ADU];
    int got = 0;
    int rc;
    ssize_t n;
    emb_pacer pace;

    emb_pacer_start(&pace, first_ms);
    while (got < sent_len) {
        rc = emb_wait_until(fd, pace.deadline);
        if (rc == -1)
            return -1;
        if (rc == 0) {
            errno = got ? EMB_EPARTIAL : ETIMEDOUT;
            return -1;
        }
        n = emb_read_some(fd, echo + got, (size_t)(sent_len - got));
        if (n < 0)
            return -1;
        if (n == 0)
            continue;
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

/* Receive one reply frame into rsp (EMB_MAX_ADU bytes): its length, 0 for an RTU frame
 * from another slave (not CRC-checked, as libmodbus), -1 with errno; the contract of
 * emb_backend.recv.  first_ms: the wait for the first byte; then byte_ms between bytes
 * (0: the whole frame within first_ms, as libmodbus), on a serial line counted from when
 * the bytes should have come (emb_pace).
 *
 * On a serial line (lk->char_ns) it reads exactly what the frame still needs
 * (emb_reply_length), never a byte past its end: what follows stays in the fd (another
 * frame that csrc/emb_io.c looks at, or stale input that the next request drops).
 *
 * On a socket it waits with poll() and then reads all that is there, up to the buffer
 * (a greedy read): a reply that came whole costs one poll() and one read(), where
 * libmodbus makes a select() and a read() per phase (function, byte count, data) and a
 * reader of exact lengths two of each.  The bytes read past the frame come back in
 * rsp after it (*got > the length): csrc/emb_io.c looks at them as it looks at the
 * pending bytes of a serial line ("the last answer wins"), and hands them back as *got
 * on entry when it calls again (a Modbus TCP reply to an earlier request skipped).  A
 * read that came back short took everything that was waiting (emb_recv_now), so
 * nothing is pending behind the frame then (lk->rx_drained) and emb_fd_pending makes
 * no call to ask. */
static int emb_fd_recv(emb_link *lk, int fd, int mbap, int slave, int first_ms,
                       int byte_ms, uint8_t *rsp, int *got)
{
    int greedy = lk->char_ns == 0;
    int n_got = greedy && *got > 0 ? *got : 0;
    int need = emb_reply_length(rsp, n_got, mbap);
    int want, rc;
    ssize_t n;
    uint16_t crc;
    emb_pacer pace;

    /* the last read filled the buffer: the rest is likely there already, so try a read
     * that does not wait before waiting (a poll() saved when it is) */
    int now = n_got > 0 && !lk->rx_drained;

    *got = n_got;
    if (!greedy)
        lk->rx_drained = 0;
    /* bytes carried over count as received just now: the byte timeout runs from here */
    emb_pacer_start(&pace, n_got > 0 && byte_ms > 0 ? byte_ms : first_ms);
    while (need >= 0 && n_got < need) {
        want = (greedy ? EMB_MAX_ADU : need) - n_got;
        if (now) {
            now = 0;
            lk->syscalls++;
            n = emb_recv_now(fd, rsp + n_got, (size_t)want);
            if (n == -1 && errno != ENOTSOCK)
                return -1;
            if (n > 0)
                goto took;
        }
        lk->syscalls++;
        rc = emb_wait_until(fd, pace.deadline);
        if (rc == -1)
            return -1;
        if (rc == 0) {
            errno = n_got ? EMB_EPARTIAL : ETIMEDOUT;
            return -1;
        }
        lk->syscalls++;
        n = emb_read_some(fd, rsp + n_got, (size_t)want);
        if (n < 0)
            return -1;
        if (n == 0)
            continue;
took:
        n_got += (int)n;
        *got = n_got;
        lk->rx_drained = greedy && n < want;
        need = emb_reply_length(rsp, n_got, mbap);
        if (need >= 0 && n_got < need)
            emb_pace(lk, &pace, (int)n, need - n_got, byte_ms);
    }
    if (need < 0) {
        errno = EMBBADDATA;
        return -1;
    }
    if (mbap)
        return need;
    if (rsp[0] != slave && rsp[0] != 0) /* 0: a broadcast address is checked, as libmodbus */
        return 0;
    crc = emb_crc16(rsp, need - 2);
    if (rsp[need - 2] != (crc & 0xFF) || rsp[need - 1] != (crc >> 8)) {
        errno = EMBBADCRC;
        return -1;
    }
    return need;
}

static int emb_rtu_recv(emb_link *lk, int fd, const emb_want *want, int first_ms,
                        int byte_ms, uint8_t *rsp, int *got)
{
    return emb_fd_recv(lk, fd, 0, want->slave, first_ms, byte_ms, rsp, got);
}

static int emb_mbap_recv(emb_link *lk, int fd, const emb_want *want, int first_ms,
                         int byte_ms, uint8_t *rsp, int *got)
{
    return emb_fd_recv(lk, fd, 1, want->slave, first_ms, byte_ms, rsp, got);
}

static int emb_mbap_check_header(const emb_link *lk, const uint8_t *rsp, int len)
{
    return emb_check_mbap(rsp, len, (long)lk->tid);
}

/* Drop whatever input is already pending (a reply we gave up on, noise, an answer to
 * a broadcast) so that it cannot be taken as the answer to the request we send next.
 * A socket: recv(MSG_DONTWAIT) until a read comes back short, one call when nothing
 * waits; a serial line (or any fd that is no socket): poll(0) and read() until poll
 * finds nothing, as emb_discard_input(fd, 0, 0, 0). */
static int emb_fd_prepare(emb_link *lk, int fd)
{
    uint8_t sink[512];
    ssize_t n;
    int rc;

    if (lk->char_ns == 0) {
        for (;;) {
            lk->syscalls++;
            n = emb_recv_now(fd, sink, sizeof sink);
            if (n == -1 && errno == ENOTSOCK)
                break;
            if (n == -1)
                return -1;
            lk->discarded += n;
            if (n < (ssize_t)sizeof sink)
                return 0;
        }
    }
    for (;;) {
        lk->syscalls++;
        rc = emb_wait_readable(fd, 0);
        if (rc == -1)
            return -1;
        if (rc == 0)
            return 0;
        lk->syscalls++;
        n = emb_read_some(fd, sink, sizeof sink);
        if (n < 0)
            return -1;
        lk->discarded += n;
    }
}

/* Bytes received and not read yet: none without asking when the socket reader's last
 * read came back short (emb_fd_recv), else FIONREAD. */
static int emb_fd_pending(emb_link *lk, int fd)
{
    if (lk->rx_drained)
        return 0;
    lk->syscalls++;
    return emb_pending(fd);
}

static long emb_fd_discard(emb_link *lk, int fd, int total_ms, int quiet_ms, int limit_ms)
{
    (void)lk;
    return emb_discard_input(fd, total_ms, quiet_ms, limit_ms);
}

/* Idle: stale input dropped, counted in lk->discarded. */
static long emb_fd_pump(emb_link *lk, int fd)
{
    return emb_fd_prepare(lk, fd) == -1 ? -1 : (long)lk->n_reports;
}

/* Bytes before the link answer nothing here: dropped, counted. */
static long emb_fd_feed(emb_link *lk, const uint8_t *data, int n)
{
    (void)data;
    lk->discarded += n;
    return lk->n_reports;
}

const emb_backend emb_rtu_backend = {
    "rtu", 1, 2, 5, emb_fd_prepare, emb_rtu_send, emb_rtu_skip_echo, emb_rtu_recv, NULL,
    emb_fd_pending, emb_fd_discard, emb_fd_pump, emb_fd_feed,
};

const emb_backend emb_mbap_backend = {
    "mbap", EMB_MBAP, 0, EMB_MBAP + 2, emb_fd_prepare, emb_mbap_send, NULL, emb_mbap_recv,
    emb_mbap_check_header, emb_fd_pending, emb_fd_discard, emb_fd_pump, emb_fd_feed,
};
