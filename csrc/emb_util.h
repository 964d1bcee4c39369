/* edgemodbus: the leaf of our C (includes nothing of ours): CRC-16, the monotonic clock,
 * and the waits and reads on a file descriptor that every link kind shares.  In the
 * cdefs: emb_now_ns, emb_crc16 (its tests) and emb_discard_input. */
#ifndef EMB_UTIL_H
#define EMB_UTIL_H

#include <stddef.h>
#include <stdint.h>
#include <sys/types.h>

uint16_t emb_crc16(const uint8_t *p, int n);
int64_t emb_now_ns(void);
void emb_sleep_until(int64_t t_ns);
int emb_wait_readable(int fd, int ms);
int emb_wait_until(int fd, int64_t deadline_ns);
int emb_eof_errno(int fd);
ssize_t emb_read_some(int fd, uint8_t *p, size_t len);
ssize_t emb_recv_now(int fd, uint8_t *p, size_t len);
int emb_pending(int fd);
int emb_write_all(int fd, const uint8_t *p, int n);
long emb_discard_input(int fd, int total_ms, int quiet_ms, int limit_ms);

#endif
