/* source_flash.c: the replay's records from flight_data.h (REPLAY_RECORDS records, written by
 * replay.py as exact hex-float constants), in flash. */
#include <string.h>

#include "flight_data.h"
#include "replay_source.h"

int replay_next(float* record) {
  static unsigned next = 0;
  if (next == REPLAY_RECORDS) return 0;
  memcpy(record, replay_data[next++], sizeof(float) * REPLAY_FIELDS);
  return 1;
}
