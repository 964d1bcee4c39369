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
 * v1.02, 6.2.2 in Appendix B); sent low byte first.  Table-driven, one lookup per byte
 * (Appendix B's example uses two 8-bit tables, auchCRCHi and auchCRCLo; this is the same
 * table as one 16-bit entry per byte value): entry b is the CRC register after b went
 * through the eight shift-and-xor steps of 6.2.2, so
 * crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF].  Constant data, not state; the lookup is
 * what the bit-by-bit loop cost (6% of a poll's CPU, docs/performance.md).
 * tests/unit/ffi/test_crc16.py checks it against a bit-by-bit reference and pymodbus. */
static const uint16_t emb_crc_table[256] = {
    0x0000, 0xC0C1, 0xC181, 0x0140, 0xC301, 0x03C0, 0x0280, 0xC241,
    0xC601, 0x06C0, 0x0780, 0xC741, 0x0500, 0xC5C1, 0xC481, 0x0440,
    0xCC01, 0x0CC0, 0x0D80, 0xCD41, 0x0F00, 0xCFC1, 0xCE81, 0x0E40,
    0x0A00, 0xCAC1, 0xCB81, 0x0B40, 0xC901, 0x09C0, 0x0880, 0xC841,
    0xD801, 0x18C0, 0x1980, 0xD941, 0x1B00, 0xDBC1, 0xDA81, 0x1A40,
    0x1E00, 0xDEC1, 0xDF81, 0x1F40, 0xDD01, 0x1DC0, 0x1C80, 0xDC41,
    0x1400, 0xD4C1, 0xD581, 0x1540, 0xD701, 0x17C0, 0x1680, 0xD641,
    0xD201, 0x12C0, 0x1380, 0xD341, 0x1100, 0xD1C1, 0xD081, 0x1040,
    0xF001, 0x30C0, 0x3180, 0xF141, 0x3300, 0xF3C1, 0xF281, 0x3240,
    0x3600, 0xF6C1, 0xF781, 0x3740, 0xF501, 0x35C0, 0x3480, 0xF441,
    0x3C00, 0xFCC1, 0xFD81, 0x3D40, 0xFF01, 0x3FC0, 0x3E80, 0xFE41,
    0xFA01, 0x3AC0, 0x3B80, 0xFB41, 0x3900, 0xF9C1, 0xF881, 0x3840,
    0x2800, 0xE8C1, 0xE981, 0x2940, 0xEB01, 0x2BC0, 0x2A80, 0xEA41,
    0xEE01, 0x2EC0, 0x2F80, 0xEF41, 0x2D00, 0xEDC1, 0xEC81, 0x2C40,
    0xE401, 0x24C0, 0x2580, 0xE541, 0x2700, 0xE7C1, 0xE681, 0x2640,
    0x2200, 0xE2C1, 0xE381, 0x2340, 0xE101, 0x21C0, 0x2080, 0xE041,
    0xA001, 0x60C0, 0x6180, 0xA141, 0x6300, 0xA3C1, 0xA281, 0x6240,
    0x6600, 0xA6C1, 0xA781, 0x6740, 0xA501, 0x65C0, 0x6480, 0xA441,
    0x6C00, 0xACC1, 0xAD81, 0x6D40, 0xAF01, 0x6FC0, 0x6E80, 0xAE41,
    0xAA01, 0x6AC0, 0x6B80, 0xAB41, 0x6900, 0xA9C1, 0xA881, 0x6840,
    0x7800, 0xB8C1, 0xB981, 0x7940, 0xBB01, 0x7BC0, 0x7A80, 0xBA41,
    0xBE01, 0x7EC0, 0x7F80, 0xBF41, 0x7D00, 0xBDC1, 0xBC81, 0x7C40,
    0xB401, 0x74C0, 0x7580, 0xB541, 0x7700, 0xB7C1, 0xB681, 0x7640,
    0x7200, 0xB2C1, 0xB381, 0x7340, 0xB101, 0x71C0, 0x7080, 0xB041,
    0x5000, 0x90C1, 0x9181, 0x5140, 0x9301, 0x53C0, 0x5280, 0x9241,
    0x9601, 0x56C0, 0x5780, 0x9741, 0x5500, 0x95C1, 0x9481, 0x5440,
    0x9C01, 0x5CC0, 0x5D80, 0x9D41, 0x5F00, 0x9FC1, 0x9E81, 0x5E40,
    0x5A00, 0x9AC1, 0x9B81, 0x5B40, 0x9901, 0x59C0, 0x5880, 0x9841,
    0x8801, 0x48C0, 0x4980, 0x8941, 0x4B00, 0x8BC1, 0x8A81, 0x4A40,
    0x4E00, 0x8EC1, 0x8F81, 0x4F40, 0x8D01, 0x4DC0, 0x4C80, 0x8C41,
    0x4400, 0x84C1, 0x8581, 0x4540, 0x8701, 0x47C0, 0x4680, 0x8641,
    0x8201, 0x42C0, 0x4380, 0x8341, 0x4100, 0x81C1, 0x8081, 0x4040,
};

uint16_t emb_crc16(const uint8_t *p, int n)
{
    uint16_t crc = 0xFFFF;
    int i;

    for (i = 0; i < n; i++)
        crc = (uint16_t)((crc >> 8) ^ emb_crc_table[(crc ^ p[i]) & 0xFF]);
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
 * returns) for up to ms: 1 readable, 0 timed out, -1 with errno.  What is left is
 * rounded up to whole milliseconds, so a timeout never ends before its time (poll()
 * never returns early; truncated, it ended up to 1 ms early). */
int emb_wait_readable(int fd, int ms)
{
    struct pollfd pfd;
    int64_t end = emb_now_ns() + (int64_t)ms * 1000000;
    int64_t left;
    int rc;

    pfd.fd = fd;
    for (;;) {
        left = (end - emb_now_ns() + 999999) / 1000000;
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

/* One recv(2) of at most len bytes that never waits (MSG_DONTWAIT, whatever the
 * socket's blocking mode): the bytes read (> 0); 0 when nothing is waiting (EAGAIN);
 * -1 with errno on an error (ENOTSOCK: fd is no socket), ECONNRESET when the peer
 * closed the connection.  A read shorter than len took everything that was waiting
 * (a stream socket's recv copies until its queue is empty or len is reached). */
ssize_t emb_recv_now(int fd, uint8_t *p, size_t len)
{
    ssize_t n;

    do
        n = recv(fd, p, len, MSG_DONTWAIT);
    while (n == -1 && errno == EINTR);
    if (n > 0)
        return n;
    if (n == 0) {
        errno = ECONNRESET;
        return -1;
    }
    return (errno == EAGAIN || errno == EWOULDBLOCK) ? 0 : -1;
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
