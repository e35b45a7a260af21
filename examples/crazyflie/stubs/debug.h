/* debug.h (replay stub): DEBUG_PRINT goes to the replay's console. */
#ifndef REPLAY_DEBUG_H
#define REPLAY_DEBUG_H
void replay_print(const char* format, ...);
#define DEBUG_PRINT(fmt, ...) replay_print(DEBUG_MODULE ": " fmt, __VA_ARGS__)
#endif
