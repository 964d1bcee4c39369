/* edgemodbus: the gateway's Modbus TCP server (see emb_serve.h).
 *
 * Framing of requests is ours (we read with poll() and recv(): libmodbus's receive uses
 * select(), which aborts on a socket fd >= 1024); replies are libmodbus's: modbus_reply
 * over a unit's modbus_mapping_t, modbus_reply_exception for every exception.  A request
 * modbus_reply would refuse is refused here first, with the code the Modbus Application
 * Protocol 1.1b3 gives (its figures 14-26: 01 function, 03 quantity or byte count, 02
 * address), because libmodbus's own refusal sleeps for the response timeout and flushes
 * the socket, which would lose a master's pipelined requests. */
#define _GNU_SOURCE /* accept4, POLLRDHUP */
#include "emb_serve.h"
#include "emb_util.h" /* emb_now_ns */

#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <stdlib.h>
#include <string.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#define EMB_SV_HDR 7       /* MBAP header (6) and the unit id */
#define EMB_SV_MAX_LEN 254 /* the MBAP length field: unit id and a PDU of at most 253 */

static void emb_sv_span(const modbus_mapping_t *m, int area, int *start, int *nb)
{
    if (m == NULL) {
        *start = 0;
        *nb = 0;
        return;
    }
    switch (area) {
    case EMB_SV_COILS: *start = m->start_bits; *nb = m->nb_bits; break;
    case EMB_SV_DISCRETE: *start = m->start_input_bits; *nb = m->nb_input_bits; break;
    case EMB_SV_HOLDING: *start = m->start_registers; *nb = m->nb_registers; break;
    default: *start = m->start_input_registers; *nb = m->nb_input_registers; break;
    }
}

emb_server *emb_sv_new(const char *ip, int port, int backlog, uint32_t max_conns,
                       int64_t idle_ns)
{
    emb_server *s;
    uint32_t i;
    int saved;

    if (max_conns == 0 || max_conns > 65536 || port < 0 || port > 65535) {
        errno = EINVAL;
        return NULL;
    }
    s = calloc(1, sizeof(*s));
    if (s == NULL)
        return NULL;
    s->listen_fd = -1;
    s->wake_fd = -1;
    s->max_conns = max_conns;
    s->idle_ns = idle_ns;
    s->conns = calloc(max_conns, sizeof(*s->conns));
    s->pfds = calloc(max_conns + 2, sizeof(struct pollfd));
    s->pidx = calloc(max_conns + 2, sizeof(*s->pidx));
    if (s->conns == NULL || s->pfds == NULL || s->pidx == NULL)
        goto fail;
    for (i = 0; i < max_conns; i++)
        s->conns[i].fd = -1;
    if (pthread_mutex_init(&s->lock, NULL) != 0) {
        errno = ENOMEM;
        goto fail_nolock;
    }
    s->ctx = modbus_new_tcp(ip, port);
    if (s->ctx == NULL)
        goto fail;
    /* libmodbus sleeps for the response timeout before the replies it refuses itself;
     * we refuse first (see above), and keep that sleep at its least should one slip by */
    modbus_set_response_timeout(s->ctx, 0, 1);
    s->listen_fd = modbus_tcp_listen(s->ctx, backlog);
    if (s->listen_fd < 0)
        goto fail;
    if (fcntl(s->listen_fd, F_SETFL, fcntl(s->listen_fd, F_GETFL) | O_NONBLOCK) < 0)
        goto fail;
    s->wake_fd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    if (s->wake_fd < 0)
        goto fail;
    return s;
fail:
    saved = errno;
    pthread_mutex_destroy(&s->lock);
    errno = saved;
fail_nolock:
    saved = errno;
    if (s->listen_fd >= 0)
        close(s->listen_fd);
    if (s->ctx != NULL)
        modbus_free(s->ctx);
    free(s->conns);
    free(s->pfds);
    free(s->pidx);
    free(s);
    errno = saved;
    return NULL;
}

int emb_sv_port(const emb_server *s)
{
    struct sockaddr_in addr;
    socklen_t len = sizeof(addr);

    if (getsockname(s->listen_fd, (struct sockaddr *)&addr, &len) < 0)
        return -1;
    return ntohs(addr.sin_port);
}

/* Set the allow-list of the server (unit -1) or of a unit: n networks (0: every
 * source) as addr, mask pairs in host byte order, each addr within its mask.  The
 * server's applies to connections accepted from now on; a unit's to every request. */
int emb_sv_allow(emb_server *s, int unit, const uint32_t *nets, uint32_t n)
{
    emb_sv_allow_list list;
    uint32_t i;

    if (unit < -1 || unit >= EMB_SV_UNITS || n > EMB_SV_NETS) {
        errno = EINVAL;
        return -1;
    }
    memset(&list, 0, sizeof(list));
    for (i = 0; i < n; i++) {
        if ((nets[2 * i] & ~nets[2 * i + 1]) != 0) {
            errno = EINVAL;
            return -1;
        }
        list.nets[i].addr = nets[2 * i];
        list.nets[i].mask = nets[2 * i + 1];
    }
    list.n = n;
    pthread_mutex_lock(&s->lock);
    if (unit < 0)
        s->allow = list;
    else
        s->unit_allow[unit] = list;
    pthread_mutex_unlock(&s->lock);
    return 0;
}

/* the lock is held: whether src is in the list (an empty list allows every source) */
static int emb_sv_allowed(const emb_sv_allow_list *list, uint32_t src)
{
    uint32_t i;

    if (list->n == 0)
        return 1;
    for (i = 0; i < list->n; i++)
        if ((src & list->nets[i].mask) == list->nets[i].addr)
            return 1;
    return 0;
}

static void emb_sv_unit_clear(emb_sv_unit *u)
{
    int a;

    if (u->map != NULL)
        modbus_mapping_free(u->map);
    u->map = NULL;
    for (a = 0; a < 4; a++) {
        free(u->state[a]);
        u->state[a] = NULL;
    }
    u->mode = EMB_SV_NONE;
}

void emb_sv_free(emb_server *s)
{
    uint32_t i;
    int u;

    if (s == NULL)
        return;
    for (i = 0; i < s->max_conns; i++)
        if (s->conns[i].fd >= 0)
            close(s->conns[i].fd);
    for (u = 0; u < EMB_SV_UNITS; u++)
        emb_sv_unit_clear(&s->units[u]);
    close(s->listen_fd);
    close(s->wake_fd);
    modbus_free(s->ctx);
    pthread_mutex_destroy(&s->lock);
    free(s->conns);
    free(s->pfds);
    free(s->pidx);
    free(s);
}

/* spans: start and count of each area (coils, discrete inputs, holding, input
 * registers), 8 ints; every address starts EMB_SV_UNMAPPED. */
int emb_sv_unit_set(emb_server *s, int unit, int mode, const int *spans)
{
    emb_sv_unit fresh;
    int a;

    if (unit < 0 || unit >= EMB_SV_UNITS) {
        errno = EINVAL;
        return -1;
    }
    memset(&fresh, 0, sizeof(fresh));
    fresh.mode = mode;
    if (mode == EMB_SV_CACHED) {
        for (a = 0; a < 4; a++)
            if (spans[2 * a] < 0 || spans[2 * a + 1] < 0
                || spans[2 * a] + spans[2 * a + 1] > 65536) {
                errno = EINVAL;
                return -1;
            }
        fresh.map = modbus_mapping_new_start_address(
            (unsigned)spans[0], (unsigned)spans[1], (unsigned)spans[2], (unsigned)spans[3],
            (unsigned)spans[4], (unsigned)spans[5], (unsigned)spans[6], (unsigned)spans[7]);
        if (fresh.map == NULL)
            return -1;
        for (a = 0; a < 4; a++) {
            fresh.state[a] = calloc(spans[2 * a + 1] ? (size_t)spans[2 * a + 1] : 1, 1);
            if (fresh.state[a] == NULL) {
                emb_sv_unit_clear(&fresh);
                errno = ENOMEM;
                return -1;
            }
        }
    }
    pthread_mutex_lock(&s->lock);
    emb_sv_unit_clear(&s->units[unit]);
    s->units[unit] = fresh;
    pthread_mutex_unlock(&s->lock);
    return 0;
}

void emb_sv_unit_fresh(emb_server *s, int unit, int64_t until_ns)
{
    if (unit < 0 || unit >= EMB_SV_UNITS)
        return;
    pthread_mutex_lock(&s->lock);
    s->units[unit].fresh_until_ns = until_ns;
    pthread_mutex_unlock(&s->lock);
}

void emb_sv_unit_stale(emb_server *s, int unit, uint64_t *out)
{
    out[EMB_SV_STALE_AGE] = out[EMB_SV_STALE_INVALID] = 0;
    if (unit < 0 || unit >= EMB_SV_UNITS)
        return;
    pthread_mutex_lock(&s->lock);
    out[EMB_SV_STALE_AGE] = s->units[unit].stale[EMB_SV_STALE_AGE];
    out[EMB_SV_STALE_INVALID] = s->units[unit].stale[EMB_SV_STALE_INVALID];
    pthread_mutex_unlock(&s->lock);
}

void emb_sv_update(emb_server *s, const emb_sv_run_op *ops, uint32_t n_ops,
                   const uint16_t *values)
{
    uint32_t k, i;

    pthread_mutex_lock(&s->lock);
    for (k = 0; k < n_ops; k++) {
        const emb_sv_run_op *op = &ops[k];
        emb_sv_unit *u = &s->units[op->unit];
        int start, nb;
        uint32_t at;

        if (u->mode != EMB_SV_CACHED || op->area > 3)
            continue;
        emb_sv_span(u->map, op->area, &start, &nb);
        if (op->start < start || op->start + op->count > start + nb)
            continue;
        at = (uint32_t)(op->start - start);
        for (i = 0; i < op->count; i++) {
            uint8_t *st = &u->state[op->area][at + i];

            *st = op->state;
            if ((op->state & 3) != EMB_SV_VALID)
                continue;
            switch (op->area) {
            case EMB_SV_COILS: u->map->tab_bits[at + i] = values[op->first + i] != 0; break;
            case EMB_SV_DISCRETE:
                u->map->tab_input_bits[at + i] = values[op->first + i] != 0;
                break;
            case EMB_SV_HOLDING: u->map->tab_registers[at + i] = values[op->first + i]; break;
            default: u->map->tab_input_registers[at + i] = values[op->first + i]; break;
            }
        }
    }
    pthread_mutex_unlock(&s->lock);
}

int emb_sv_post(emb_server *s, int conn, uint32_t gen, int kind, const uint8_t *data,
                int len)
{
    emb_sv_conn *c;
    uint64_t one = 1;
    ssize_t rc;

    if (conn < 0 || (uint32_t)conn >= s->max_conns || len < 0
        || len > EMB_SV_ADU - EMB_SV_HDR) {
        errno = EINVAL;
        return -1;
    }
    c = &s->conns[conn];
    pthread_mutex_lock(&s->lock);
    if (c->fd < 0 || c->gen != gen || !c->busy || c->ready) {
        pthread_mutex_unlock(&s->lock);
        return 0; /* the connection is gone (or was answered): dropped */
    }
    if (len > 0) /* data may be NULL when there is none (memcpy's arguments may not) */
        memcpy(c->out, data, (size_t)len);
    c->out_len = len;
    c->out_kind = kind;
    c->ready = 1;
    pthread_mutex_unlock(&s->lock);
    rc = write(s->wake_fd, &one, sizeof(one));
    (void)rc; /* a full eventfd is awake already */
    return 1;
}

void emb_sv_stop(emb_server *s)
{
    uint64_t one = 1;
    ssize_t rc;

    __atomic_store_n(&s->stop, 1, __ATOMIC_SEQ_CST);
    rc = write(s->wake_fd, &one, sizeof(one));
    (void)rc;
}

int emb_sv_open_connections(emb_server *s)
{
    uint32_t i;
    int n = 0;

    for (i = 0; i < s->max_conns; i++)
        n += s->conns[i].fd >= 0;
    return n;
}

/* the lock is held */
static void emb_sv_close(emb_sv_conn *c, uint64_t *counter)
{
    int fd = c->fd;

    c->fd = -1; /* the slot and the counter first: a master that sees the close finds */
    c->busy = 0; /* both up to date */
    c->ready = 0;
    c->have = 0;
    (*counter)++;
    close(fd);
}

static uint32_t emb_sv_frame_len(const emb_sv_conn *c)
{
    return 6u + (((uint32_t)c->buf[4] << 8) | c->buf[5]);
}

/* the lock is held: 0 sent, -1 the connection is to be closed.  An exception reply's
 * function is the request's with the high bit set (Application Protocol 1.1b3, 7).
 * libmodbus adds 0x80, which wraps for a function code of 0x80 or more (no request has
 * one: that range is the exception replies', 4.1) into a normal reply's code (0xFF ->
 * 0x7F); such a request is answered here with its own code. */
static int emb_sv_exception(emb_server *s, emb_sv_conn *c, int code)
{
    if (code > 0 && code < 12)
        s->c.exceptions[code]++;
    if (c->buf[EMB_SV_HDR] & 0x80) {
        uint8_t adu[EMB_SV_HDR + 2];

        memcpy(adu, c->buf, 4); /* transaction and protocol ids */
        adu[4] = 0;
        adu[5] = 3; /* unit id, function, code */
        adu[6] = c->buf[6];
        adu[7] = c->buf[EMB_SV_HDR];
        adu[8] = (uint8_t)code;
        return send(c->fd, adu, sizeof(adu), MSG_NOSIGNAL) == (ssize_t)sizeof(adu) ? 0 : -1;
    }
    modbus_set_socket(s->ctx, c->fd);
    return modbus_reply_exception(s->ctx, c->buf, (unsigned)code) < 0 ? -1 : 0;
}

/* the lock is held: 0 if every address of [addr, addr + nb) of the unit's area may be
 * read (or written), else the exception code; a read answered 0B is counted by why (an
 * item Invalid first: its own reason says more than the unit's age) */
static int emb_sv_check(emb_sv_unit *u, int area, uint32_t addr, uint32_t nb,
                        int writing, int64_t now)
{
    int start, count;
    uint32_t i, at;
    int invalid = 0;

    emb_sv_span(u->map, area, &start, &count);
    if (addr < (uint32_t)start || addr + nb > (uint32_t)start + (uint32_t)count)
        return MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS;
    at = addr - (uint32_t)start;
    for (i = 0; i < nb; i++) {
        uint8_t st = u->state[area][at + i];

        if ((st & 3) == EMB_SV_UNMAPPED || (writing && !(st & EMB_SV_WRITABLE)))
            return MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS;
        invalid |= (st & 3) == EMB_SV_INVALID;
    }
    if (!writing && (invalid || now > u->fresh_until_ns)) {
        u->stale[invalid ? EMB_SV_STALE_INVALID : EMB_SV_STALE_AGE]++;
        return MODBUS_EXCEPTION_GATEWAY_TARGET;
    }
    return 0;
}

/* the lock is held.  A request of a cached unit: the exception code to answer, 0 for a
 * read to answer from the image, -2 for a write to hand to Python. */
static int emb_sv_cached(emb_sv_unit *u, const uint8_t *adu, uint32_t n, int64_t now)
{
    const uint8_t *pdu = adu + EMB_SV_HDR;
    uint32_t len = n - EMB_SV_HDR;
    int fc = pdu[0];
    uint32_t addr, qty, count;
    int rc;

    if (fc < 1 || (fc > 6 && fc != 0x0F && fc != 0x10))
        return MODBUS_EXCEPTION_ILLEGAL_FUNCTION;
    if (len < 5)
        return MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE;
    addr = ((uint32_t)pdu[1] << 8) | pdu[2];
    qty = ((uint32_t)pdu[3] << 8) | pdu[4];
    switch (fc) {
    case 1:
    case 2:
    case 3:
    case 4:
        if (len != 5 || qty < 1 || qty > (fc <= 2 ? 2000u : 125u))
            return MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE;
        return emb_sv_check(u, fc == 1 ? EMB_SV_COILS : fc == 2 ? EMB_SV_DISCRETE
                                : fc == 3 ? EMB_SV_HOLDING : EMB_SV_INPUT,
                            addr, qty, 0, now);
    case 5:
    case 6:
        if (len != 5 || (fc == 5 && qty != 0 && qty != 0xFF00))
            return MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE;
        rc = emb_sv_check(u, fc == 5 ? EMB_SV_COILS : EMB_SV_HOLDING, addr, 1, 1, now);
        return rc ? rc : -2;
    default: /* 0x0F, 0x10 */
        if (len < 6)
            return MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE;
        count = pdu[5];
        if (qty < 1 || qty > (fc == 0x0F ? 1968u : 123u)
            || count != (fc == 0x0F ? (qty + 7) / 8 : 2 * qty) || len != 6 + count)
            return MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE;
        rc = emb_sv_check(u, fc == 0x0F ? EMB_SV_COILS : EMB_SV_HOLDING, addr, qty, 1, now);
        return rc ? rc : -2;
    }
}

/* One complete request at the front of c's buffer: answer it, or hand it to Python (1).
 * Returns -1 when the connection is to be closed. */
static int emb_sv_request(emb_server *s, emb_sv_conn *c, uint32_t conn, uint32_t n,
                          int64_t now)
{
    emb_sv_unit *u = &s->units[c->buf[6]];
    int rc;

    s->c.requests++;
    c->last_ns = now;
    pthread_mutex_lock(&s->lock);
    if (u->mode == EMB_SV_NONE) {
        rc = emb_sv_exception(s, c, MODBUS_EXCEPTION_GATEWAY_PATH);
    } else if (!emb_sv_allowed(&s->unit_allow[c->buf[6]], c->src)) {
        s->c.refused_unit++; /* answered as a unit not served: nothing more is told */
        rc = emb_sv_exception(s, c, MODBUS_EXCEPTION_GATEWAY_PATH);
    } else if (u->mode == EMB_SV_FORWARD) {
        rc = -2;
    } else {
        rc = emb_sv_cached(u, c->buf, n, now);
        if (rc == 0) {
            /* counted before it is sent, as the exceptions are: a master that holds
             * the reply and reads the counters finds it counted */
            s->c.cached_replies++;
            modbus_set_socket(s->ctx, c->fd);
            rc = modbus_reply(s->ctx, c->buf, (int)n, u->map) < 0 ? -1 : 0;
        } else if (rc > 0) {
            rc = emb_sv_exception(s, c, rc);
        }
    }
    if (rc == -2) {
        c->busy = 1;
        s->ev_conn = (int)conn;
        s->ev_gen = c->gen;
        s->ev_len = (int)n;
        s->ev_src = c->src;
        memcpy(s->ev_adu, c->buf, n);
        s->c.to_python++;
        pthread_mutex_unlock(&s->lock);
        return 1;
    }
    pthread_mutex_unlock(&s->lock);
    return rc;
}

/* Drop the request answered (n bytes) from the front of c's buffer. */
static void emb_sv_consume(emb_sv_conn *c, uint32_t n)
{
    memmove(c->buf, c->buf + n, c->have - n);
    c->have -= n;
}

/* Serve the complete requests buffered on non-busy connections; 1 when one went to
 * Python (the event is set). */
static int emb_sv_serve_buffered(emb_server *s, int64_t now)
{
    uint32_t i;

    for (i = 0; i < s->max_conns; i++) {
        emb_sv_conn *c = &s->conns[i];

        while (c->fd >= 0 && !c->busy && c->have >= 6) {
            uint32_t n;
            int rc;

            if (c->buf[2] != 0 || c->buf[3] != 0 || emb_sv_frame_len(c) < 6 + 2
                || emb_sv_frame_len(c) > 6 + EMB_SV_MAX_LEN) {
                /* not Modbus (protocol id 0) or a length no request has: close */
                pthread_mutex_lock(&s->lock);
                emb_sv_close(c, &s->c.closed_bad);
                pthread_mutex_unlock(&s->lock);
                break;
            }
            n = emb_sv_frame_len(c);
            if (c->have < n)
                break;
            rc = emb_sv_request(s, c, i, n, now);
            if (rc == 1)
                return 1; /* consumed once Python answered */
            if (rc < 0) {
                pthread_mutex_lock(&s->lock);
                emb_sv_close(c, &s->c.closed_bad);
                pthread_mutex_unlock(&s->lock);
                break;
            }
            emb_sv_consume(c, n);
        }
    }
    return 0;
}

/* Send the answers Python posted. */
static void emb_sv_flush_posts(emb_server *s, int64_t now)
{
    uint32_t i;

    pthread_mutex_lock(&s->lock);
    for (i = 0; i < s->max_conns; i++) {
        emb_sv_conn *c = &s->conns[i];
        uint32_t n;
        int rc = 0;

        if (c->fd < 0 || !c->busy || !c->ready)
            continue;
        n = emb_sv_frame_len(c);
        if (c->out_kind == EMB_SV_POST_EXCEPTION) {
            rc = emb_sv_exception(s, c, c->out[0]);
        } else if (c->out_kind == EMB_SV_POST_WRITTEN) {
            emb_sv_unit *u = &s->units[c->buf[6]];
            /* the unit may have been set anew meanwhile: then the image cannot take it */
            if (u->mode == EMB_SV_CACHED && emb_sv_cached(u, c->buf, n, now) == -2) {
                modbus_set_socket(s->ctx, c->fd);
                rc = modbus_reply(s->ctx, c->buf, (int)n, u->map) < 0 ? -1 : 0;
            } else {
                rc = emb_sv_exception(s, c, MODBUS_EXCEPTION_SLAVE_OR_SERVER_FAILURE);
            }
        } else {
            /* a forwarded reply PDU: the request's MBAP header with the reply's length */
            uint8_t adu[EMB_SV_ADU];
            uint32_t len = (uint32_t)c->out_len;
            ssize_t sent;

            memcpy(adu, c->buf, EMB_SV_HDR);
            adu[4] = (uint8_t)((len + 1) >> 8);
            adu[5] = (uint8_t)(len + 1);
            memcpy(adu + EMB_SV_HDR, c->out, len);
            if (len == 2 && (c->out[0] & 0x80) && c->out[1] < 12)
                s->c.exceptions[c->out[1]]++;
            sent = send(c->fd, adu, EMB_SV_HDR + len, MSG_NOSIGNAL);
            rc = sent == (ssize_t)(EMB_SV_HDR + len) ? 0 : -1;
        }
        if (rc < 0) {
            emb_sv_close(c, &s->c.closed_bad);
            continue;
        }
        c->busy = 0;
        c->ready = 0;
        c->last_ns = now;
        emb_sv_consume(c, n);
    }
    pthread_mutex_unlock(&s->lock);
}

/* Seconds accepting pauses after accept4 failed for want of fds or memory: from the
 * first, doubling up to the last (as the DTU listener, src/edgemodbus/line/dtu_listener.py);
 * the pending connection stays in the backlog, and polling the listening socket
 * meanwhile would report it at once, again and again: a spin. */
#define EMB_SV_ACCEPT_PAUSE_MIN_NS 50000000LL
#define EMB_SV_ACCEPT_PAUSE_MAX_NS 2000000000LL

static void emb_sv_accept_failed(emb_server *s, int err, int64_t now)
{
    int64_t pause = s->accept_pause_ns ? 2 * s->accept_pause_ns : EMB_SV_ACCEPT_PAUSE_MIN_NS;

    if (pause > EMB_SV_ACCEPT_PAUSE_MAX_NS)
        pause = EMB_SV_ACCEPT_PAUSE_MAX_NS;
    s->accept_pause_ns = pause;
    s->accept_at_ns = now + pause;
    __atomic_store_n(&s->c.accept_errno, err, __ATOMIC_RELAXED);
    __atomic_add_fetch(&s->c.accept_errors, 1, __ATOMIC_RELAXED);
}

static void emb_sv_accept(emb_server *s, int64_t now)
{
    for (;;) {
        struct sockaddr_in peer;
        socklen_t peer_len = sizeof(peer);
        int fd = accept4(s->listen_fd, (struct sockaddr *)&peer, &peer_len,
                         SOCK_NONBLOCK | SOCK_CLOEXEC);
        int one = 1, allowed;
        uint32_t i, src;

        if (fd < 0) {
            int err = errno;

            if (err == EMFILE || err == ENFILE || err == ENOBUFS || err == ENOMEM)
                emb_sv_accept_failed(s, err, now);
            return; /* EAGAIN, or an error of that one connection */
        }
        s->accept_pause_ns = 0;
        /* the listening socket is IPv4 (modbus_tcp_listen) */
        src = peer.sin_family == AF_INET ? ntohl(peer.sin_addr.s_addr) : 0;
        pthread_mutex_lock(&s->lock);
        allowed = emb_sv_allowed(&s->allow, src);
        pthread_mutex_unlock(&s->lock);
        if (!allowed) {
            struct linger reset = {1, 0};

            s->c.refused_source++;
            setsockopt(fd, SOL_SOCKET, SO_LINGER, &reset, sizeof(reset)); /* RST */
            close(fd);
            continue;
        }
        for (i = 0; i < s->max_conns && s->conns[i].fd >= 0; i++)
            ;
        if (i == s->max_conns) {
            s->c.refused++; /* counted first, as in emb_sv_close */
            close(fd); /* over the cap */
            continue;
        }
        setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
        pthread_mutex_lock(&s->lock);
        s->conns[i].fd = fd;
        s->conns[i].src = src;
        s->conns[i].gen++;
        s->conns[i].busy = 0;
        s->conns[i].ready = 0;
        s->conns[i].have = 0;
        s->conns[i].last_ns = now;
        pthread_mutex_unlock(&s->lock);
        s->c.accepted++;
    }
}

static void emb_sv_read(emb_server *s, emb_sv_conn *c)
{
    ssize_t rc = recv(c->fd, c->buf + c->have, sizeof(c->buf) - c->have, 0);

    if (rc > 0) {
        c->have += (uint32_t)rc;
        return;
    }
    if (rc < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR))
        return;
    pthread_mutex_lock(&s->lock);
    emb_sv_close(c, &s->c.closed_peer);
    pthread_mutex_unlock(&s->lock);
}

int emb_sv_run(emb_server *s, int64_t until_ns)
{
    struct pollfd *pfds = s->pfds;

    for (;;) {
        int64_t now = emb_now_ns();
        int64_t wake_at = until_ns;
        uint32_t i, n = 0;
        int64_t wait_ns;
        int rc;

        if (__atomic_load_n(&s->stop, __ATOMIC_SEQ_CST))
            return EMB_SV_EV_STOP;
        emb_sv_flush_posts(s, now);
        if (emb_sv_serve_buffered(s, now))
            return EMB_SV_EV_REQUEST;
        if (now >= until_ns)
            return EMB_SV_EV_DEADLINE;
        pfds[n].fd = s->wake_fd;
        pfds[n++].events = POLLIN;
        /* accepting paused after an accept error: poll() skips a negative fd */
        pfds[n].fd = now < s->accept_at_ns ? -1 : s->listen_fd;
        pfds[n++].events = POLLIN;
        if (now < s->accept_at_ns && s->accept_at_ns < wake_at)
            wake_at = s->accept_at_ns;
        for (i = 0; i < s->max_conns; i++) {
            emb_sv_conn *c = &s->conns[i];

            if (c->fd < 0)
                continue;
            if (!c->busy && s->idle_ns > 0) {
                if (now - c->last_ns >= s->idle_ns) {
                    pthread_mutex_lock(&s->lock);
                    emb_sv_close(c, &s->c.closed_idle);
                    pthread_mutex_unlock(&s->lock);
                    continue;
                }
                if (c->last_ns + s->idle_ns < wake_at)
                    wake_at = c->last_ns + s->idle_ns;
            }
            s->pidx[n] = i;
            pfds[n].fd = c->fd;
            pfds[n++].events = c->busy ? POLLRDHUP : POLLIN;
        }
        wait_ns = wake_at - now;
        if (wait_ns > 60000000000LL)
            wait_ns = 60000000000LL;
        rc = poll(pfds, n, (int)((wait_ns + 999999) / 1000000));
        if (rc < 0) {
            if (errno == EINTR)
                continue;
            return EMB_SV_EV_ERROR;
        }
        if (rc == 0)
            continue;
        if (pfds[0].revents) {
            uint64_t count;
            ssize_t got = read(s->wake_fd, &count, sizeof(count));
            (void)got;
        }
        now = emb_now_ns();
        if (pfds[1].revents & POLLIN)
            emb_sv_accept(s, now);
        for (i = 2; i < n; i++) {
            emb_sv_conn *c = &s->conns[s->pidx[i]];

            if (c->fd != pfds[i].fd || !pfds[i].revents)
                continue;
            if (c->busy) {
                /* a master that left while Python holds its request (a FIN
                 * is POLLRDHUP): its slot is freed, the answer will be dropped */
                if (pfds[i].revents & (POLLRDHUP | POLLHUP | POLLERR)) {
                    pthread_mutex_lock(&s->lock);
                    emb_sv_close(c, &s->c.closed_peer);
                    pthread_mutex_unlock(&s->lock);
                }
                continue;
            }
            emb_sv_read(s, c);
        }
    }
}
