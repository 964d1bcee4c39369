/* libFuzzer harness for the DTU stream framing in csrc/emb_stream.c (heartbeats, wrapped
 * report frames, the report ring), built by tools/fuzz.py with clang
 * -fsanitize=fuzzer,address,undefined and linked with Debian's libmodbus.
 *
 * Each input scripts a DTU (or an edge MCU) on a stream link: bytes that came before the
 * link (emb_feed), bytes the peer sends once a request went out (the other end of a
 * socketpair, written the moment the request is sent, as in fuzz_frames.c), or bytes
 * that arrive while the link is idle (emb_pump, then a short emb_link_discard).  The C
 * files are included (fuzz_io_hooks.h) so that the send hooks below see each request.  The
 * reply and report buffers are malloc'ed at exactly the sizes the API requires, so any
 * access past them is an ASan report.  Contracts checked: every report taken is a whole
 * wrapped frame (header, a length its function code allows, 0D tail, CRC); a successful
 * read or write answers its request (slave, function, byte count, register address for
 * wrapped frames, a write's echo) and the values are the reply's; the ring and the
 * receive buffer never hold more than they can.
 *
 * Input layout (missing bytes read as 0):
 *   ctl   bit0 wrapped frames, else plain RTU with a heartbeat; bit1 echo option (plain
 *         only); bits2-3 op: 0 feed, 1 read, 2 write (transact), 3 idle (pump, discard);
 *         bit4 append the RTU CRC to each scripted frame; bit5 wrap each scripted frame
 *         in FF AA | the request's address | frame | 0D; bit6 the peer closes after its
 *         bytes; bit7 take the reports after every chunk (else at the end)
 *   heartbeat  length u8 (% 9) and its bytes
 *   slave u8, function u8 (read: 1 + % 4), addr u16, nb u16 (% 126 registers, % 2001 bits)
 *   [pdu]  op write: length u8 and the bytes (its first 3 bytes are made a write's
 *          function code and address)
 *   chunks n u8 (% 6), each: length u8 and the bytes (fixed up per bits 4 and 5)
 *   the rest: raw bytes sent after the chunks
 */
#include "fuzz_io_hooks.h" /* the code under test sends through the hooks below */

#include <stdio.h>
#include <stdlib.h>

#define FUZZ_NAME "fuzz_stream"
#include "fuzz_input.h"

static struct script {
    int peer;
    int crc, wrap, close_after, armed;
    unsigned address;
    reader chunks; /* n u8, then (len u8, bytes) per chunk, then raw bytes */
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

/* The n-th scripted chunk, fixed up as the control bits say, appended to S.out. */
static void put_chunk(const uint8_t *body, unsigned len)
{
    uint8_t head[4] = {0xFF, 0xAA, (uint8_t)(S.address >> 8), (uint8_t)S.address};
    uint8_t crc[2];
    uint16_t c = emb_crc16(body, (int)len);
    uint8_t tail = 0x0D;

    crc[0] = (uint8_t)(c & 0xFF);
    crc[1] = (uint8_t)(c >> 8);
    if (S.wrap)
        put(head, 4);
    put(body, len);
    if (S.crc)
        put(crc, 2);
    if (S.wrap)
        put(&tail, 1);
}

static void answer(void)
{
    reader r = S.chunks;
    unsigned n = rd8(&r) % 6;

    if (!S.armed)
        return;
    S.armed = 0;
    S.len = 0;
    for (unsigned k = 0; k < n; k++) {
        uint8_t body[256];
        unsigned len = rd8(&r);
        for (unsigned i = 0; i < len; i++)
            body[i] = rd8(&r);
        put_chunk(body, len);
    }
    put(r.p, r.n);
    if (S.len)
        (void)send(S.peer, S.out, S.len, MSG_NOSIGNAL | MSG_DONTWAIT);
    if (S.close_after)
        shutdown(S.peer, SHUT_WR);
}

static int fuzz_send_raw_request(modbus_t *ctx, const uint8_t *req, int len)
{
    int rc = modbus_send_raw_request(ctx, req, len);
    if (rc != -1)
        answer();
    return rc;
}

static ssize_t fuzz_send(int fd, const void *buf, size_t n, int flags)
{
    ssize_t rc = send(fd, buf, n, flags);
    if (rc == (ssize_t)n && fd != S.peer)
        answer();
    return rc;
}

/* A report taken from the ring is a whole, valid wrapped frame. */
static void check_report(const uint8_t *p, int n)
{
    const uint8_t *rtu = p + EMB_WRAP_PREFIX;
    int len = n - EMB_WRAP_PREFIX - 1;
    uint16_t c;

    CHECK(n >= EMB_WRAP_PREFIX + 5 + 1 && n <= EMB_REPORT_MAX);
    CHECK(p[0] == 0xFF && p[1] == 0xAA && p[n - 1] == 0x0D);
    c = emb_crc16(rtu, len - 2);
    CHECK(rtu[len - 2] == (c & 0xFF) && rtu[len - 1] == (c >> 8));
    if (rtu[1] & 0x80)
        CHECK(len == 5);
    else if (rtu[1] >= 1 && rtu[1] <= 4)
        CHECK(len == 5 + rtu[2] && rtu[2] > 0 && !(rtu[1] >= 3 && rtu[2] % 2));
    else if (rtu[1] == 22)
        CHECK(len == 10);
    else
        CHECK(len == 8 && (rtu[1] == 5 || rtu[1] == 6 || rtu[1] == 15 || rtu[1] == 16));
}

static void take_reports(emb_link *lk, uint8_t *report)
{
    int n;

    CHECK(lk->n_before <= lk->n_reports);
    CHECK(lk->rx_len <= EMB_RX_SIZE && lk->ring_used <= EMB_RING_SIZE);
    while ((n = emb_report_take(lk, report)) > 0)
        check_report(report, n);
    CHECK(lk->n_reports == 0 && lk->n_before == 0 && lk->ring_used == 0);
}

/* A successful read: the reply answers the request and dest holds its data. */
static void check_read(const emb_link *lk, int slave, int function, int nb, const void *dest,
                       const uint8_t *rsp)
{
    int bits = function <= 2;
    int count = bits ? (nb + 7) / 8 : 2 * nb;
    int len = lk->rsp_len;
    uint16_t c = emb_crc16(rsp, len - 2);

    CHECK(len == 3 + count + 2);
    CHECK(rsp[len - 2] == (c & 0xFF) && rsp[len - 1] == (c >> 8));
    CHECK(rsp[0] == slave && rsp[1] == function && rsp[2] == count);
    for (int i = 0; i < nb; i++) {
        if (bits)
            CHECK(((const uint8_t *)dest)[i] == ((rsp[3 + i / 8] >> (i % 8)) & 1));
        else
            CHECK(((const uint16_t *)dest)[i] == (uint16_t)(rsp[3 + 2 * i] << 8 | rsp[4 + 2 * i]));
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *input, size_t size)
{
    reader r = {input, size};
    uint8_t ctl = rd8(&r);
    int op = (ctl >> 2) & 3;
    unsigned hb_len = rd8(&r) % 9;
    uint8_t hb[8];
    for (unsigned i = 0; i < hb_len; i++)
        hb[i] = rd8(&r);
    int slave = rd8(&r);
    int function = 1 + rd8(&r) % 4;
    int addr = rd16(&r);
    int nb = rd16(&r) % (function <= 2 ? 2001 : 126); /* 0 is refused */
    uint8_t pdu[256];
    int pdu_len = 0;
    static const uint8_t writes[] = {5, 6, 15, 16, 22};
    if (op == 2) {
        pdu_len = rd8(&r) % 254;
        for (int i = 0; i < pdu_len; i++)
            pdu[i] = rd8(&r);
        if (pdu_len < 3)
            pdu_len = 3;
        pdu[0] = writes[pdu[0] % 5];
        pdu[1] = (uint8_t)(addr >> 8);
        pdu[2] = (uint8_t)addr;
    }

    int sv[2];
    if (socketpair(AF_UNIX, SOCK_STREAM, 0, sv) == -1)
        return 0;
    memset(&S, 0, sizeof S);
    S.peer = sv[1];
    S.crc = (ctl >> 4) & 1;
    S.wrap = (ctl >> 5) & 1;
    S.close_after = (ctl >> 6) & 1;
    S.address = (unsigned)addr;
    S.chunks = r;

    modbus_t *ctx = modbus_new_rtu("/dev/null", 9600, 'N', 8, 1);
    emb_link *lk = calloc(1, sizeof *lk);
    emb_stream_buf *sb = malloc(sizeof *sb); /* exactly its size: ASan sees any overrun */
    uint8_t *rsp = malloc(EMB_MAX_ADU);
    uint8_t *report = malloc(EMB_REPORT_MAX);
    void *dest = malloc(nb ? (size_t)nb * (function <= 2 ? 1 : 2) : 1);
    if (!ctx || !lk || !sb || !rsp || !report || !dest)
        abort();
    lk->sb = sb;
    modbus_set_socket(ctx, sv[0]);
    modbus_set_response_timeout(ctx, 0, 2000);
    modbus_set_byte_timeout(ctx, 0, 1000);
    lk->wrapped = ctl & 1;
    if (lk->wrapped) { /* the report ring: a wrapped link's only (src/edgemodbus/_ffi/context.py) */
        lk->ring = malloc(EMB_RING_SIZE);
        if (!lk->ring)
            abort();
    }
    lk->echo = lk->wrapped ? 0 : (ctl >> 1) & 1;
    lk->hb_len = lk->wrapped || hb_len ? hb_len : 1;
    memcpy(lk->hb, hb, hb_len);
    if (!lk->wrapped && !hb_len)
        lk->hb[0] = 0xFE; /* a plain stream link has a heartbeat */

    int rc, err;
    errno = 0;
    if (op == 0) {
        /* bytes before the link, chunk by chunk */
        reader c = S.chunks;
        unsigned n = rd8(&c) % 6;
        for (unsigned k = 0; k < n; k++) {
            uint8_t body[256];
            unsigned len = rd8(&c);
            for (unsigned i = 0; i < len; i++)
                body[i] = rd8(&c);
            S.len = 0;
            put_chunk(body, len);
            CHECK(emb_feed(lk, S.out, (int)S.len) == (long)lk->n_reports);
            if (ctl & 0x80)
                take_reports(lk, report);
        }
        emb_feed(lk, c.p, (int)c.n);
    } else if (op == 1) {
        S.armed = 1;
        rc = emb_read(ctx, lk, slave, function, addr, nb, dest, rsp);
        err = errno;
        CHECK(rc == -1 ? err != 0 : rc == nb);
        if (rc == nb)
            check_read(lk, slave, function, nb, dest, rsp);
    } else if (op == 2) {
        S.armed = 1;
        rc = emb_transact(ctx, lk, slave, pdu, pdu_len, rsp);
        err = errno;
        CHECK(rc == -1 ? err != 0 : rc > 0);
        if (rc > 0) { /* a write's reply repeats the request (6.5, 6.6, 6.11, 6.12, 6.16) */
            int echo = pdu[0] == 0x16 ? 7 : 5;
            CHECK(rsp[0] == slave && rsp[1] == pdu[0] && rc == lk->rsp_len);
            if (pdu_len >= echo && (pdu[0] == 5 || pdu[0] == 6 || pdu[0] == 0x0F ||
                                    pdu[0] == 0x10 || pdu[0] == 0x16))
                CHECK(rc == 1 + echo + 2 && memcmp(rsp + 1, pdu, (size_t)echo) == 0);
        }
        if (rc == -1 && err >= EMB_EEXCEPTION && err < EMB_EEXCEPTION + 256)
            CHECK(rsp[0] == slave && rsp[1] == (pdu[0] | 0x80) &&
                  rsp[2] == err - EMB_EEXCEPTION);
    } else {
        S.armed = 1;
        answer();
        CHECK(emb_pump(ctx, lk) >= -1);
        CHECK(emb_link_discard(ctx, lk, 1, 1, 2) >= -1);
    }
    take_reports(lk, report);
    CHECK(lk->rsp_len >= 0 && lk->rsp_len <= EMB_MAX_ADU && lk->discarded >= 0);
    CHECK(lk->heartbeats >= 0 && lk->dropped >= 0 && lk->reports_lost >= 0);

    modbus_free(ctx);
    close(sv[0]);
    close(sv[1]);
    free(lk->ring);
    free(lk);
    free(sb);
    free(rsp);
    free(report);
    free(dest);
    return 0;
}
