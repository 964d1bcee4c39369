/* edgemodbus: transaction helpers around libmodbus 3.1.6.
 *
 * Each function does a whole step (select the slave, send, receive) so that the
 * Python bus worker makes one C call, with the GIL released, per Modbus transaction.
 * No globals, no allocation: callers own every buffer. */
#include "emb_io.h"

#include <errno.h>
#include <poll.h>
#include <time.h>
#include <unistd.h>

/* Drop whatever input is already pending (a reply we gave up on, noise, an answer to
 * a broadcast) so that it cannot be taken as the answer to the request we send next:
 * RTU frames carry no transaction id (Modbus over Serial Line v1.02, 2.5.1). */
static void emb_drop_pending(modbus_t *ctx)
{
    int saved = errno;

    (void)emb_discard_input(modbus_get_socket(ctx), 0, 0);
    errno = saved;
}

/* Read one block with function code 1, 2, 3 or 4 (Modbus Application Protocol
 * v1.1b3, 6.1-6.4).  dest holds nb bytes (bits, one per byte) or nb registers. */
int emb_read(modbus_t *ctx, int slave, int function, int addr, int nb, void *dest)
{
    if (modbus_set_slave(ctx, slave) == -1)
        return -1;
    emb_drop_pending(ctx);
    switch (function) {
    case 1:
        return modbus_read_bits(ctx, addr, nb, (uint8_t *)dest);
    case 2:
        return modbus_read_input_bits(ctx, addr, nb, (uint8_t *)dest);
    case 3:
        return modbus_read_registers(ctx, addr, nb, (uint16_t *)dest);
    case 4:
        return modbus_read_input_registers(ctx, addr, nb, (uint16_t *)dest);
    default:
        errno = EINVAL;
        return -1;
    }
}

/* Send a request PDU prefixed with the slave id (req[0] = slave, req[1] = function)
 * and receive the whole confirmation ADU into rsp (at least 260 bytes).  The caller
 * checks the reply (echo, exception, lengths): libmodbus 3.1.6 only checks the CRC
 * and, on RTU, that the slave id matches (returning 0 when it does not). */
int emb_transact_raw(modbus_t *ctx, int slave, const uint8_t *req, int req_len, uint8_t *rsp)
{
    if (modbus_set_slave(ctx, slave) == -1)
        return -1;
    emb_drop_pending(ctx);
    if (modbus_send_raw_request(ctx, req, req_len) == -1)
        return -1;
    return modbus_receive_confirmation(ctx, rsp);
}

/* Send without waiting for a reply: broadcast (slave 0) requests get none
 * (Modbus over Serial Line v1.02, 2.1). */
int emb_send_raw(modbus_t *ctx, int slave, const uint8_t *req, int req_len)
{
    if (modbus_set_slave(ctx, slave) == -1)
        return -1;
    return modbus_send_raw_request(ctx, req, req_len);
}

static long emb_elapsed_ms(const struct timespec *since)
{
    struct timespec now;

    clock_gettime(CLOCK_MONOTONIC, &now);
    return (long)(now.tv_sec - since->tv_sec) * 1000L +
           (long)(now.tv_nsec - since->tv_nsec) / 1000000L;
}

/* Discard input on fd.  RTU frames carry no transaction id, so a reply that comes
 * after the response timeout would be taken as the answer to the next request.
 * Waits up to total_ms for stray bytes, returning early once quiet_ms pass with
 * nothing new after the last byte; total_ms = 0 only takes what is already there.
 * Uses poll(), not select(): fds of 1024 and more are safe here.
 * Returns the number of bytes discarded, or -1 with errno set (ECONNRESET when the
 * peer closed the connection). */
long emb_discard_input(int fd, int total_ms, int quiet_ms)
{
    uint8_t sink[512];
    struct timespec start;
    long discarded = 0;
    long waited;
    struct pollfd pfd;
    int timeout;
    int rc;
    ssize_t n;

    clock_gettime(CLOCK_MONOTONIC, &start);
    pfd.fd = fd;
    for (;;) {
        waited = emb_elapsed_ms(&start);
        timeout = total_ms > waited ? (int)(total_ms - waited) : 0;
        if (discarded > 0 && quiet_ms < timeout)
            timeout = quiet_ms;
        pfd.events = POLLIN;
        pfd.revents = 0;
        rc = poll(&pfd, 1, timeout);
        if (rc == -1) {
            if (errno == EINTR)
                continue;
            return -1;
        }
        if (rc == 0)
            return discarded;
        if (pfd.revents & (POLLERR | POLLNVAL)) {
            errno = EIO;
            return -1;
        }
        n = read(fd, sink, sizeof(sink));
        if (n == 0) {
            errno = ECONNRESET;
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
