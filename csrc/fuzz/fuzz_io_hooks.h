/* edgemodbus fuzz harnesses of the reader: compile the transaction code (csrc/emb_io.c),
 * every link kind (csrc/emb_rtu.c, csrc/emb_stream.c), the reply check (csrc/emb_check.c)
 * and the leaf (csrc/emb_util.c) into the harness with libmodbus's
 * modbus_send_raw_request and the socket send() redirected to the harness's
 * fuzz_send_raw_request and fuzz_send, which script the peer's reply.  Shared by
 * fuzz_frames.c and fuzz_stream.c; not part of the module. */
#ifndef EMB_FUZZ_IO_HOOKS_H
#define EMB_FUZZ_IO_HOOKS_H

#include <stddef.h>
#include <stdint.h>
#include <sys/types.h>

#include <modbus.h>

static int fuzz_send_raw_request(modbus_t *ctx, const uint8_t *req, int len);
static ssize_t fuzz_send(int fd, const void *buf, size_t n, int flags);
#define modbus_send_raw_request fuzz_send_raw_request
#define send fuzz_send
#include "../emb_util.c"
#include "../emb_check.c"
#include "../emb_rtu.c"
#include "../emb_stream.c"
#include "../emb_io.c"
#undef send
#undef modbus_send_raw_request
int modbus_send_raw_request(modbus_t *ctx, const uint8_t *raw_req, int raw_req_length);
ssize_t send(int fd, const void *buf, size_t n, int flags);

#endif
