/* replay_source.h: where the replay's records come from (source_stdin.c on the host,
 * source_flash.c under QEMU). A record is one sample period of a flight, REPLAY_FIELDS floats:
 * the motion-capture pose (position [m], quaternion x, y, z, w) and whether there is one, the
 * accelerometer [g] and whether there is a sample, the gyroscope [deg/s], the four motor PWM
 * ratios (0-65535) and the battery voltage [V]. */
#ifndef REPLAY_SOURCE_H
#define REPLAY_SOURCE_H

#define REPLAY_POSE 0
#define REPLAY_POSE_VALID 7
#define REPLAY_ACC 8
#define REPLAY_ACC_VALID 11
#define REPLAY_GYRO 12
#define REPLAY_MOTORS 15
#define REPLAY_VBAT 19
#define REPLAY_FIELDS 20

/* The next record into record; 0 when the flight is over. */
int replay_next(float* record);
#endif
