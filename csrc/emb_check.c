/* edgemodbus: the one reply check (see emb_check.h), and the reply length a frame's
 * header tells, which every receiving link kind frames by.  Modbus Application Protocol
 * v1.1b3 ch. 6 (each function's reply) and ch. 7 (exception responses); Modbus Messaging
 * on TCP/IP v1.0b 3.1.3 (the MBAP header).  No globals, no allocation. */
#include "emb_check.h"

#include <string.h>

/* Length of the reply ADU whose first `got` bytes are in p, as its header tells it
 * (ch. 6: a read reply carries a byte count, 6.1-6.4; a write reply echoes a fixed-size
 * part of the request, 6.5, 6.6, 6.11, 6.12, 6.16; an exception reply is function | 0x80
 * and one code, ch. 7); while fewer than header + 2 bytes came: that many (every reply
 * has them), so a read of what this returns never goes past the frame's end.  -1: the
 * byte count does not fit in an ADU (libmodbus's EMBBADDATA).  Function codes of unknown
 * length are framed as libmodbus frames them (the function and one byte), on Modbus TCP
 * by the MBAP length when it is plausible. */
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

/* The reply PDU a request PDU (p, n bytes) calls for: *count the byte count a reply must
 * carry (-1: none, or the slave chooses it: 0x11), *echo the bytes of the request a reply
 * must repeat (0: none).  Returns the reply PDU's length, 0 when any length will do (a
 * function we do not know, a request too short to tell). */
static int emb_expect(const uint8_t *p, int n, int *count, int *echo)
{
    int qty = n >= 5 ? (p[3] << 8) | p[4] : 0; /* 6.1-6.4, 6.17: the (read) quantity */

    *count = -1;
    *echo = 0;
    switch (n >= 1 ? p[0] : 0) {
    case 0x01: case 0x02: /* 6.1, 6.2: the bits packed into bytes */
        if (n < 5)
            return 0;
        *count = (qty + 7) / 8;
        return 2 + *count;
    case 0x03: case 0x04: case 0x17: /* 6.3, 6.4, 6.17: two bytes per register */
        if (n < 5)
            return 0;
        *count = 2 * qty;
        return 2 + *count;
    case 0x05: case 0x06: case 0x0F: case 0x10: /* 6.5, 6.6, 6.11, 6.12: address and
                                                 * value, or address and quantity */
        if (n < 5)
            return 0;
        *echo = 5;
        return 5;
    case 0x16: /* 6.16: the whole request */
        if (n < 7)
            return 0;
        *echo = 7;
        return 7;
    default:
        return 0;
    }
}

/* Whether rsp (rsp_len bytes: the unit id, then the reply PDU) answers req (req_len
 * bytes: the unit id, then the request PDU).  Returns 0 with *exc = -1 for a normal
 * reply, 0 with *exc = the code (0..255) for an exception response to the request's
 * function (ch. 7), else the EMB_E* errno saying why not, in this order: too short
 * (EMB_ECOUNT), another unit (EMB_ESLAVE), an exception response of another length
 * (EMB_ELENGTH) or for another function (EMB_EOTHEREXC), another function
 * (EMB_EFUNCTION), a read's byte count (EMB_ECOUNT: 6.1-6.4, 6.17), the reply's length
 * (EMB_ELENGTH; 0x11, 6.13: the byte count's), a write's echo (EMB_EWECHO: 6.5, 6.6,
 * 6.11, 6.12, 6.16).  Functions not named here are checked up to their function code. */
int emb_check_reply(const uint8_t *req, int req_len, const uint8_t *rsp, int rsp_len,
                    int *exc)
{
    const uint8_t *p = rsp + 1;
    int n = rsp_len - 1;
    int fc, want, count, echo;

    *exc = -1;
    if (req_len < 2 || rsp_len < 3)
        return EMB_ECOUNT;
    if (rsp[0] != req[0])
        return EMB_ESLAVE;
    fc = req[1];
    if (p[0] == (fc | 0x80)) {
        if (n != 2)
            return EMB_ELENGTH;
        *exc = p[1];
        return 0;
    }
    if (p[0] & 0x80)
        return EMB_EOTHEREXC;
    if (p[0] != fc)
        return EMB_EFUNCTION;
    if (fc == 0x11) /* 6.13: the byte count says the length the slave chose */
        return n >= 3 && p[1] == n - 2 ? 0 : EMB_ELENGTH;
    want = emb_expect(req + 1, req_len - 1, &count, &echo);
    if (count >= 0 && p[1] != count)
        return EMB_ECOUNT;
    if (want && n != want)
        return EMB_ELENGTH;
    if (echo && memcmp(p + 1, req + 2, (size_t)(echo - 1)) != 0)
        return EMB_EWECHO;
    return 0;
}

/* The MBAP header of a reply ADU (len bytes): its transaction id (tid < 0: not
 * checked), protocol id 0, and the length of what follows it.  0 or the EMB_E* errno. */
int emb_check_mbap(const uint8_t *adu, int len, long tid)
{
    if (len < EMB_MBAP + 2)
        return EMB_ECOUNT;
    if (tid >= 0 && ((adu[0] << 8) | adu[1]) != tid)
        return EMB_ETID;
    if (adu[2] != 0 || adu[3] != 0)
        return EMB_EPROTOID;
    if (((adu[4] << 8) | adu[5]) != len - 6)
        return EMB_EMBAPLEN;
    return 0;
}

/* emb_check_reply for a whole reply ADU to pdu sent to slave: on Modbus TCP (mbap) the
 * MBAP header first (emb_check_mbap), else an RTU frame whose CRC was checked when it was
 * received (its last 2 bytes are not looked at).  For callers that hold an ADU. */
int emb_check_adu(int mbap, long tid, int slave, const uint8_t *pdu, int pdu_len,
                  const uint8_t *adu, int adu_len, int *exc)
{
    uint8_t req[EMB_MAX_ADU];
    int h = mbap ? EMB_MBAP : 1;
    int err;

    *exc = -1;
    if (pdu_len < 1 || pdu_len > EMB_MAX_ADU - 1 || adu_len < h + 2 + (mbap ? 0 : 2))
        return EMB_ECOUNT;
    if (mbap && (err = emb_check_mbap(adu, adu_len, tid)) != 0)
        return err;
    req[0] = (uint8_t)slave;
    memcpy(req + 1, pdu, (size_t)pdu_len);
    return emb_check_reply(req, pdu_len + 1, adu + h - 1, adu_len - (h - 1) - (mbap ? 0 : 2),
                           exc);
}
