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
    (void)lk;
    if (emb_rtu_frame(slave, pdu, pdu_len, sent, sent_len) == -1)
        return -1;
    if (modbus_set_slave(ctx, slave) == -1)
        return -1;
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

/* Receive one reply frame into rsp with poll() and read(), reading exactly what the
 * frame still needs (emb_reply_length), never a byte past its end: what follows stays in
 * the fd (another frame that csrc/emb_io.c looks at, or stale input that the next
 * request drops).  first_ms: the wait for the first byte; then byte_ms between bytes
 * (0: the whole frame within first_ms, as libmodbus), on a serial line counted from when
 * the bytes should have come (emb_pace).  The contract of emb_backend.recv; an RTU frame
 * from another slave is not CRC-checked (libmodbus does the same). */
static int emb_fd_recv(emb_link *lk, int fd, int mbap, int slave, int first_ms,
                       int byte_ms, uint8_t *rsp, int *got)
{
    int need = emb_reply_length(rsp, 0, mbap);
    int n_got = 0;
    int rc;
    ssize_t n;
    uint16_t crc;
    emb_pacer pace;

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
        n = emb_read_some(fd, rsp + n_got, (size_t)(need - n_got));
        if (n < 0)
            return -1;
        if (n == 0)
            continue;
        n_got += (int)n;
        *got = n_got;
        need = emb_reply_length(rsp, n_got, mbap);
        if (need < 0) {
            errno = EMBBADDATA;
            return -1;
        }
        if (n_got >= need)
            break;
        emb_pace(lk, &pace, (int)n, need - n_got, byte_ms);
    }
    if (mbap)
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
 * a broadcast) so that it cannot be taken as the answer to the request we send next. */
static int emb_fd_prepare(emb_link *lk, int fd)
{
    long n = emb_discard_input(fd, 0, 0, 0);

    if (n == -1)
        return -1;
    lk->discarded += n;
    return 0;
}

static int emb_fd_pending(emb_link *lk, int fd)
{
    (void)lk;
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
