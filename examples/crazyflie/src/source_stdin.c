/* source_stdin.c: the replay's records from standard input, REPLAY_FIELDS native floats each. */
#include <stdio.h>

#include "replay_source.h"

int replay_next(float* record) {
  return fread(record, sizeof(float), REPLAY_FIELDS, stdin) == REPLAY_FIELDS;
}
