/* edgemodbus: one link of the loop engine as a non-blocking state machine: a DTU stream
 * (plain RTU with heartbeats or an echo, or wrapped frames with their reports) or a
 * Modbus TCP link (MBAP), polled through the line engine's devices (csrc/emb_edev.h) and
 * fault policy steps (csrc/emb_fault.h), on a loop thread's epoll set and deadline heap
 * (csrc/emb_loop.h); its I/O, framing each kind as the blocking engine's backends
 * do, is csrc/emb_loop_io.c. */
#ifndef EMB_LOOP_LINK_H
#define EMB_LOOP_LINK_H

#include "emb_loop_io.h" /* emb_loop_link, EMB_LS_* */

int emb_loop_link_run(emb_loop *lp, emb_loop_link *k);

#endif
