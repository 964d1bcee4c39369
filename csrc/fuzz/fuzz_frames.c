/* libFuzzer harness for our reply handling in csrc/emb_io.c (emb_read, emb_transact,
 * emb_send: stale-input drop, echo skip, reply checks, "last answer wins", data
 * extraction) over the plain RTU and Modbus TCP link kinds of csrc/emb_rtu.c and the one
 * reply check of csrc/emb_check.c, built by tools/fuzz.py with clang -fsanitize=fuzzer,address,undefined and
 * linked with Debian's libmodbus, which sends the RTU requests as in production.
 *
 * Each input scripts what a slave (or a DTU, or noise) sends back: the bytes are written
 * into the other end of a socketpair the moment the request has been sent, so the real
 * code path runs: our reader (the backend's recv) frames them, our checks decide.  The C
 * files are included here (fuzz_io_hooks.h) so that the send hooks below see each
 * request; nothing else of them changes.  The reply buffer is malloc'ed at the
 * 260 bytes the API requires and the destination at exactly nb elements, so any access
 * past them is an ASan report.  On success the harness checks that the reply really
 * answers the request (slave or unit id, MBAP transaction id, protocol id and length,
 * function, byte count) and that the values are the reply's data: no reply that fails a
 * check is ever taken.
 *
 * Input layout (missing bytes read as 0):
 *   ctl   bit0 Modbus TCP (MBAP) else RTU; bit1 echo option; bits2-3 op: 0/1 read,
 *         2 transact (a raw PDU), 3 send; bit4 put the request's echo first;
 *         bit5 fix up each scripted frame (RTU: append its CRC; MBAP: prepend a header
 *         with the request's transaction id and the right length); bit6 the first
 *         fixed-up MBAP frame carries another transaction id; bit7 the peer closes
 *         the connection after its bytes
 *   slave u8, function u8 (read: 1 + % 4), addr u16, nb u16, tid u16 (the last one sent;
 *         RTU: its low 2 bits x 500 ns are the character time, so the reader paces)
 *   stale  n u8 (% 32) and n bytes already waiting before the request (a late reply)
 *   [pdu]  op transact/send: length u8 and the bytes
 *   frames n u8 (% 5), each: length u8 and the bytes (fixed up per bit5)
 *   the rest: raw bytes sent after the frames
 */
#include "fuzz_io_hooks.h" /* the code under test sends through the hooks below */

#include <stdio.h>
#include <stdlib.h>

#define FUZZ_NAME "fuzz_frames"
#include "fuzz_input.h"

/* What the peer sends once the request is out. */
static struct script {
    int peer;           /* the other end of the socketpair */
    int mbap, fixup, echo_first, wrong_tid, close_after;
    reader frames;      /* n u8, then (len u8, bytes) per frame, then raw bytes */
    uint8_t out[8192];
    size_t len;
} S;

static void put(const void *p, size_t n)
{
    if (S.len + n <= sizeof S.out) {
        memcpy(S.out + S.len, p, n);
        S.len += n;
    }
}

/* Build the peer's bytes for the request `req` (the ADU without the RTU CRC) and send
 * them in one write, so that libmodbus finds them all as it reads. */
static void answer(const uint8_t *req, int req_len, unsigned tid)
{
    reader r = S.frames;
    S.len = 0;
    if (S.echo_first) {
        uint8_t crc[2];
        uint16_t c = emb_crc16(req, req_len);
        crc[0] = (uint8_t)(c & 0xFF);
        crc[1] = (uint8_t)(c >> 8);
        put(req, (size_t)req_len);
        if (!S.mbap)
            put(crc, 2);
    }
    unsigned n = rd8(&r) % 5;
    for (unsigned k = 0; k < n; k++) {
        uint8_t body[256];
        unsigned len = rd8(&r);
        for (unsigned i = 0; i < len; i++)
            body[i] = rd8(&r);
        if (!S.fixup) {
            put(body, len);
        } else if (S.mbap) {
            unsigned t = S.wrong_tid && k == 0 ? tid ^ 1u : tid;
            uint8_t h[6] = {(uint8_t)(t >> 8), (uint8_t)t, 0, 0, (uint8_t)(len >> 8),
                            (uint8_t)len};
            put(h, 6);
            put(body, len);
        } else {
            uint16_t c = emb_crc16(body, (int)len);
            uint8_t crc[2] = {(uint8_t)(c & 0xFF), (uint8_t)(c >> 8)};
            put(body, len);
            put(crc, 2);
        }
    }
    put(r.p, r.n); /* trailing noise */
    if (S.len)
        (void)send(S.peer, S.out, S.len, MSG_NOSIGNAL | MSG_DONTWAIT);
    if (S.close_after)
        shutdown(S.peer, SHUT_WR); /* the peer hangs up: EOF after its bytes */
}

static int fuzz_send_raw_request(modbus_t *ctx, const uint8_t *req, int len)
{
    int rc = modbus_send_raw_request(ctx, req, len);
    if (rc != -1)
        answer(req, len, 0);
    return rc;
}

static ssize_t fuzz_send(int fd, const void *buf, size_t n, int flags)
{
    ssize_t rc = send(fd, buf, n, flags);
    if (rc == (ssize_t)n && n >= EMB_MBAP) { /* emb_send_adu writes an MBAP ADU at once */
        const uint8_t *b = buf;
        answer(b, (int)n, (unsigned)(b[0] << 8 | b[1]));
    }
    return rc;
}

/* A successful read: the reply in rsp answers the request and dest holds its data. */
static void check_read(const emb_link *lk, int slave, int function, int nb,
                       const void *dest, const uint8_t *rsp)
{
    int h = lk->mbap ? EMB_MBAP : 1;
    int bits = function <= 2;
    int count = bits ? (nb + 7) / 8 : 2 * nb;
    int len = lk->rsp_len;
    CHECK(len == h + 2 + count + (lk->mbap ? 0 : 2));
    if (lk->mbap) {
        CHECK((unsigned)(rsp[0] << 8 | rsp[1]) == lk->tid);
        CHECK(rsp[2] == 0 && rsp[3] == 0);
        CHECK((rsp[4] << 8 | rsp[5]) == len - 6);
    } else {
        uint16_t c = emb_crc16(rsp, len - 2);
        CHECK(rsp[len - 2] == (c & 0xFF) && rsp[len - 1] == (c >> 8));
    }
    CHECK(rsp[h - 1] == slave && rsp[h] == function && rsp[h + 1] == count);
    const uint8_t *data = rsp + h + 2;
    for (int i = 0; i < nb; i++) {
        if (bits)
            CHECK(((const uint8_t *)dest)[i] == ((data[i / 8] >> (i % 8)) & 1));
        else
            CHECK(((const uint16_t *)dest)[i] == (uint16_t)(data[2 * i] << 8 | data[2 * i + 1]));
    }
}

/* A normal reply PDU (n bytes) taken for the request PDU: what Modbus Application
 * Protocol v1.1b3 ch. 6 says it must hold, written here apart from csrc/emb_check.c. */
static void check_answer(const uint8_t *pdu, int pdu_len, const uint8_t *reply, int n)
{
    int fc = pdu[0];
    int qty = pdu_len >= 5 ? pdu[3] << 8 | pdu[4] : 0;

    if (pdu_len < 5)
        return;
    if (fc == 1 || fc == 2)
        CHECK(n == 2 + (qty + 7) / 8 && reply[1] == (qty + 7) / 8);
    else if (fc == 3 || fc == 4 || fc == 0x17)
        CHECK(n == 2 + 2 * qty && reply[1] == 2 * qty);
    else if (fc == 5 || fc == 6 || fc == 0x0F || fc == 0x10)
        CHECK(n == 5 && memcmp(reply, pdu, 5) == 0);
    else if (fc == 0x16 && pdu_len >= 7)
        CHECK(n == 7 && memcmp(reply, pdu, 7) == 0);
}

/* A transaction's outcome: a normal reply to the request's function, or an exception
 * response to it (errno EMB_EEXCEPTION + code), each with the right header. */
static void check_transact(const emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                           int rc, int err, const uint8_t *rsp)
{
    int h = lk->mbap ? EMB_MBAP : 1;
    int exception = rc == -1 && err >= EMB_EEXCEPTION && err < EMB_EEXCEPTION + 256;
    if (rc == -1 && !exception)
        return;
    int len = lk->rsp_len;
    CHECK(rc == -1 || rc == len);
    CHECK(len >= h + 2 && len <= EMB_MAX_ADU);
    if (lk->mbap) {
        CHECK((unsigned)(rsp[0] << 8 | rsp[1]) == lk->tid);
        CHECK(rsp[2] == 0 && rsp[3] == 0 && (rsp[4] << 8 | rsp[5]) == len - 6);
    }
    CHECK(rsp[h - 1] == slave);
    if (exception) {
        CHECK(rsp[h] == (pdu[0] | 0x80) && rsp[h + 1] == err - EMB_EEXCEPTION);
        return;
    }
    CHECK(rsp[h] == pdu[0]);
    check_answer(pdu, pdu_len, rsp + h, len - h - (lk->mbap ? 0 : 2));
}

int LLVMFuzzerTestOneInput(const uint8_t *input, size_t size)
{
    reader r = {input, size};
    uint8_t ctl = rd8(&r);
    int slave = rd8(&r);
    int function = 1 + rd8(&r) % 4;
    int addr = rd16(&r);
    int nb = rd16(&r) % 2002; /* 0 and 2001 are refused */
    unsigned tid = rd16(&r);
    int op = (ctl >> 2) & 3;
    uint8_t stale[32];
    unsigned n_stale = rd8(&r) % 32;
    for (unsigned i = 0; i < n_stale; i++)
        stale[i] = rd8(&r);
    uint8_t pdu[256];
    int pdu_len = 0;
    if (op >= 2) {
        pdu_len = rd8(&r); /* 254 and 255 are refused */
        for (int i = 0; i < pdu_len; i++)
            pdu[i] = rd8(&r);
    }

    int sv[2];
    if (socketpair(AF_UNIX, SOCK_STREAM, 0, sv) == -1)
        return 0;
    memset(&S, 0, sizeof S);
    S.peer = sv[1];
    S.mbap = ctl & 1;
    S.echo_first = (ctl >> 4) & 1;
    S.fixup = (ctl >> 5) & 1;
    S.wrong_tid = (ctl >> 6) & 1;
    S.close_after = (ctl >> 7) & 1;
    S.frames = r;
    if (n_stale)
        (void)send(sv[1], stale, n_stale, MSG_NOSIGNAL | MSG_DONTWAIT);

    modbus_t *ctx = S.mbap ? modbus_new_tcp("127.0.0.1", 502)
                           : modbus_new_rtu("/dev/null", 9600, 'N', 8, 1);
    if (!ctx)
        abort();
    modbus_set_socket(ctx, sv[0]);
    modbus_set_response_timeout(ctx, 0, 2000); /* everything is sent at once: short */
    modbus_set_byte_timeout(ctx, 0, 1000);
    emb_link lk;
    memset(&lk, 0, sizeof lk);
    lk.mbap = S.mbap;
    lk.echo = (ctl >> 1) & 1;
    lk.tid = tid;
    if (!lk.mbap)
        lk.char_ns = (tid & 3u) * 500u; /* a serial line's pacing: sleeps, never sooner */

    uint8_t *rsp = malloc(EMB_MAX_ADU);
    size_t elem = function <= 2 ? 1 : 2;
    void *dest = malloc(nb ? (size_t)nb * elem : 1);
    if (!rsp || !dest)
        abort();
    memset(rsp, 0, EMB_MAX_ADU);
    int rc, err;
    errno = 0;
    if (op < 2) {
        rc = emb_read(ctx, &lk, slave, function, addr, nb, dest, rsp);
        err = errno;
        CHECK(rc == -1 ? err != 0 : rc == nb);
        if (rc == nb)
            check_read(&lk, slave, function, nb, dest, rsp);
    } else if (op == 2) {
        rc = emb_transact(ctx, &lk, slave, pdu, pdu_len, rsp);
        err = errno;
        CHECK(rc == -1 ? err != 0 : rc > 0);
        check_transact(&lk, slave, pdu, pdu_len, rc, err, rsp);
    } else {
        rc = emb_send(ctx, &lk, slave, pdu, pdu_len);
        CHECK(rc == 0 || rc == -1);
    }
    CHECK(lk.rsp_len >= 0 && lk.rsp_len <= EMB_MAX_ADU && lk.discarded >= 0);

    modbus_free(ctx); /* does not close the socket: ours */
    close(sv[0]);
    close(sv[1]);
    free(rsp);
    free(dest);
    return 0;
}
