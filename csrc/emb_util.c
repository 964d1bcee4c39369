/* edgemodbus: CRC-16, the monotonic clock and the fd waits (see emb_util.h).  poll(), not
 * select(): fds of 1024 and more are safe here.  No globals, no allocation. */
#include "emb_util.h"

#include <errno.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

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

/* CLOCK_MONOTONIC in nanoseconds: the one clock of the reader, the stream framing, the
 * line engine and the Modbus TCP server. */
int64_t emb_now_ns(void)
{
    struct timespec now;

    clock_gettime(CLOCK_MONOTONIC, &now);
    return (int64_t)now.tv_sec * 1000000000LL + now.tv_nsec;
}

/* Sleep until the monotonic clock reaches t_ns. */
void emb_sleep_until(int64_t t_ns)
{
    struct timespec ts;

    ts.tv_sec = (time_t)(t_ns / 1000000000);
    ts.tv_nsec = (long)(t_ns % 1000000000);
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR)
        ;
}

/* Wait until fd is readable (or reports a hangup or an error, which the next read
 * returns) for up to ms: 1 readable, 0 timed out, -1 with errno. */
int emb_wait_readable(int fd, int ms)
{
    struct pollfd pfd;
    int64_t end = emb_now_ns() + (int64_t)ms * 1000000;
    int64_t left;
    int rc;

    pfd.fd = fd;
    for (;;) {
        left = (end - emb_now_ns()) / 1000000;
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

/* Wait until fd is readable or the monotonic clock passes deadline_ns: 1, 0, -1. */
int emb_wait_until(int fd, int64_t deadline_ns)
{
    int64_t left = deadline_ns - emb_now_ns();

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

/* One read(2) of at most len bytes: the bytes read (> 0); 0 when nothing was read and
 * the caller may wait and try again (EINTR, EAGAIN); -1 with errno on an error, end of
 * file as emb_eof_errno. */
ssize_t emb_read_some(int fd, uint8_t *p, size_t len)
{
    ssize_t n = read(fd, p, len);

    if (n > 0)
        return n;
    if (n == 0) {
        errno = emb_eof_errno(fd);
        return -1;
    }
    return (errno == EINTR || errno == EAGAIN) ? 0 : -1;
}

/* Bytes already received on fd and not read yet (0 if the driver cannot tell). */
int emb_pending(int fd)
{
    int n = 0;

    if (ioctl(fd, FIONREAD, &n) == -1)
        return 0;
    return n;
}

/* Write all n bytes to a socket (no SIGPIPE: a closed peer is EPIPE).  0, or -1. */
int emb_write_all(int fd, const uint8_t *p, int n)
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
    int64_t start = emb_now_ns();
    long discarded = 0;
    long waited;
    long timeout;
    int rc;
    ssize_t n;

    if (limit_ms < total_ms)
        limit_ms = total_ms;
    for (;;) {
        waited = (long)((emb_now_ns() - start) / 1000000);
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
        n = emb_read_some(fd, sink, sizeof(sink));
        if (n < 0)
            return -1;
        discarded += n;
    }
}
