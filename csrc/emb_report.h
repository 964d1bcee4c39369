/* edgemodbus: wrapped reports applied by the line engine in C (see emb_report.c). */
#ifndef EMB_REPORT_H
#define EMB_REPORT_H

#include "emb_edev.h"

int emb_reports_apply(emb_engine *e, int cur_dev, const emb_eblock *cur_block);
long emb_decode_range(emb_plan *p, const uint32_t *span, const void *data, uint32_t count,
                      uint32_t lo, uint32_t hi, uint32_t *found);

#endif
