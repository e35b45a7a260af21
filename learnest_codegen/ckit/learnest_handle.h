/* learnest_handle.h -- what every estimator's handle starts with, and the names of the API.
 *
 * Include after learnest_kit.h with LEARNEST_PREFIX (the build's symbol prefix),
 * LEARNEST_NU and LEARNEST_NY. The public functions are LEARNEST_API(name) = <prefix>_<name>, the handle
 * LEARNEST_HANDLE = struct <prefix>_handle (the header's <prefix>_t), whose first member is
 * struct learnest_common c (learnest_api.h reads it).
 */
#ifndef LEARNEST_HANDLE_H
#define LEARNEST_HANDLE_H

#include "learnest_gate.h"

#ifndef LEARNEST_PREFIX
#error "learnest_handle.h: define LEARNEST_PREFIX (the symbol prefix of the build)"
#endif

#define LEARNEST_API(name) LEARNEST_CAT(LEARNEST_PREFIX, LEARNEST_CAT(_, name))
#define LEARNEST_HANDLE struct LEARNEST_API(handle)

struct learnest_common {
  uint32_t magic;                /* LEARNEST_MAGIC once init succeeded */
  int samples;                   /* samples taken since init/reset (saturates at INT_MAX) */
  int rejections;                /* outputs the gate rejected since init/reset */
  int rejected[LEARNEST_NY];     /* the outputs the gate rejected in the last step */
  struct learnest_gate gate;
  learnest_real u_held[LEARNEST_NU];  /* the last accepted input (learnest_api.h's check) */
  int input_rejected[LEARNEST_NU];    /* the input components replaced in the last step */
  int input_rejections;               /* input components replaced since init/reset */
};

#endif /* LEARNEST_HANDLE_H */
