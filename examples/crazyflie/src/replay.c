/* replay.c: a generated Crazyflie app (its estimator_out_of_tree.c, compiled as it is) fed a
 * recorded flight in the order the firmware would feed it.
 *
 * The app is included whole, so that the replay reaches its task round and its last sample; it
 * is compiled against the firmware's own headers (estimator.h, stabilizer_types.h, math3d.h,
 * param.h, log.h, ...) and the stubs of ../stubs for what needs the kernel or the drivers.
 * Each record of the flight (replay_source.h) is one sample period, 1000 / APP_SAMPLE_RATE_HZ
 * stabilizer ticks. On every tick the IMU's gyroscope and accelerometer samples go into the
 * measurement queue (the recorded values, held over the period); on the period's last tick the
 * motion-capture pose (when the record has one), the motor PWM ratios and the battery voltage
 * are set. Each tick then runs the stabilizer's side (estimatorOutOfTree) and the app task's
 * round, as the scheduler would. Each record prints one line,
 *
 *     s <k> <started> <status> <valid> <u...> <y...> <x...> <busy_sample> <busy_other>
 *
 * with the sample's inputs, measurement and validity flags as the app gave them to the
 * estimator, and its estimate, every number as the 8 hex digits of its float32 bits (x is "-"
 * before the estimator has started); busy_* are the sample clock's ticks spent in the period's
 * last tick and in its other ticks together. A summary line closes the run. */
#include <stdarg.h>
#include <stdint.h>
#include <string.h>

#include "estimator_out_of_tree.c"
#include "../../cortex_m/src/platform.h" /* the QEMU and host platforms of examples/cortex_m */
#include "replay_source.h"

#define TICKS_PER_SAMPLE (RATE_MAIN_LOOP / APP_SAMPLE_RATE_HZ)
#define QUEUE_SIZE 20 /* the firmware's MEASUREMENTS_QUEUE_SIZE */

static measurement_t queue[QUEUE_SIZE];
static unsigned queueHead, queueCount;
static uint16_t motorRatio[4];
static float batteryVoltage;

bool estimatorDequeue(measurement_t* m) {
  if (!queueCount) return false;
  *m = queue[queueHead];
  queueHead = (queueHead + 1u) % QUEUE_SIZE;
  --queueCount;
  return true;
}

static void enqueue(const measurement_t* m) {
  if (queueCount == QUEUE_SIZE) replay_fail("the measurement queue overflowed");
  queue[(queueHead + queueCount) % QUEUE_SIZE] = *m;
  ++queueCount;
}

uint16_t motorsGetRatio(uint32_t id) { return motorRatio[id]; }
float pmGetBatteryVoltage(void) { return batteryVoltage; }
uint64_t usecTimestamp(void) { return 0; }
void replay_print(const char* format, ...) { (void)format; }

static char* put_text(char* p, const char* text) {
  while (*text) *p++ = *text++;
  return p;
}

static char* put_uint(char* p, uint64_t v) {
  char digits[20];
  int n = 0;
  do {
    digits[n++] = (char)('0' + v % 10u);
    v /= 10u;
  } while (v);
  while (n) *p++ = digits[--n];
  return p;
}

static char* put_int(char* p, int v) {
  if (v < 0) *p++ = '-';
  return put_uint(p, v < 0 ? 0u - (uint64_t)v : (uint64_t)v);
}

static char* put_bits(char* p, float v) {
  static const char hex[] = "0123456789abcdef";
  uint32_t bits;
  int shift;
  memcpy(&bits, &v, sizeof bits);
  *p++ = ' ';
  for (shift = 28; shift >= 0; shift -= 4) *p++ = hex[(bits >> shift) & 0xfu];
  return p;
}

static void write_line(char* start, char* end) {
  *end++ = '\n';
  platform_write(start, (size_t)(end - start));
}

void replay_fail(const char* why) {
  char line[128];
  char* p = put_text(put_text(line, "error "), why);
  write_line(line, p);
  platform_exit(1);
}

/* The queue entries of one tick: the IMU's, and on the sample's tick the pose. */
static void feed(const float* r, int sampleTick) {
  measurement_t m;
  memset(&m, 0, sizeof m);
  m.type = MeasurementTypeGyroscope;
  m.data.gyroscope.gyro.x = r[REPLAY_GYRO + 0];
  m.data.gyroscope.gyro.y = r[REPLAY_GYRO + 1];
  m.data.gyroscope.gyro.z = r[REPLAY_GYRO + 2];
  enqueue(&m);
  if (r[REPLAY_ACC_VALID] != 0.0f) {
    memset(&m, 0, sizeof m);
    m.type = MeasurementTypeAcceleration;
    m.data.acceleration.acc.x = r[REPLAY_ACC + 0];
    m.data.acceleration.acc.y = r[REPLAY_ACC + 1];
    m.data.acceleration.acc.z = r[REPLAY_ACC + 2];
    enqueue(&m);
  }
  if (sampleTick) {
    int i;
    for (i = 0; i < 4; ++i) motorRatio[i] = (uint16_t)r[REPLAY_MOTORS + i];
    batteryVoltage = r[REPLAY_VBAT];
    if (r[REPLAY_POSE_VALID] != 0.0f) {
      memset(&m, 0, sizeof m);
      m.type = MeasurementTypePose;
      m.data.pose.x = r[REPLAY_POSE + 0];
      m.data.pose.y = r[REPLAY_POSE + 1];
      m.data.pose.z = r[REPLAY_POSE + 2];
      m.data.pose.quat.x = r[REPLAY_POSE + 3];
      m.data.pose.quat.y = r[REPLAY_POSE + 4];
      m.data.pose.quat.z = r[REPLAY_POSE + 5];
      m.data.pose.quat.w = r[REPLAY_POSE + 6];
      enqueue(&m);
    }
  }
}

int main(void) {
  static char line[512];
  float record[REPLAY_FIELDS];
  app_real x[APP_NX];
  state_t state;
  stabilizerStep_t tick = 0;
  uint32_t k = 0, busySampleMax = 0, busyOtherMax = 0;
  uint64_t busySampleTotal = 0, busyOtherTotal = 0;
  int i;
  char* p;

  platform_start(0.5);
  estimatorOutOfTreeInit();
  for (; replay_next(record); ++k) {
    uint32_t busySample = 0, busyOther = 0;
    int t;
    for (t = 1; t <= TICKS_PER_SAMPLE; ++t) {
      uint32_t start;
      feed(record, t == TICKS_PER_SAMPLE);
      start = platform_busy_ticks();
      estimatorOutOfTree(&state, ++tick);
      taskRound();
      if (t == TICKS_PER_SAMPLE) {
        busySample = platform_busy_ticks() - start;
      } else {
        const uint32_t busy = platform_busy_ticks() - start;
        busyOther += busy;
        busyOtherMax = busy > busyOtherMax ? busy : busyOtherMax;
      }
    }
    if (tick % TICKS_PER_SAMPLE) replay_fail("the sample's tick is not a sample tick");
    busySampleMax = busySample > busySampleMax ? busySample : busySampleMax;
    busySampleTotal += busySample;
    busyOtherTotal += busyOther;
    p = put_text(line, "s ");
    p = put_uint(p, k);
    *p++ = ' ';
    *p++ = started ? '1' : '0';
    *p++ = ' ';
    p = put_int(p, lastStatus);
    *p++ = ' ';
    for (i = 0; i < APP_NY; ++i) *p++ = sample.valid[i] ? '1' : '0';
    for (i = 0; i < APP_NU; ++i) p = put_bits(p, sample.u[i]);
    for (i = 0; i < APP_NY; ++i) p = put_bits(p, sample.y[i]);
    if (started && APP_GET_STATE(estimator, x) == LEARNEST_OK) {
      for (i = 0; i < APP_NX; ++i) p = put_bits(p, x[i]);
    } else {
      p = put_text(p, " -");
    }
    *p++ = ' ';
    p = put_uint(p, busySample);
    *p++ = ' ';
    p = put_uint(p, busyOther);
    write_line(line, p);
  }
  p = put_text(line, "summary samples=");
  p = put_uint(p, k);
  p = put_text(p, " steps=");
  p = put_uint(p, steps);
  p = put_text(p, " rejected=");
  p = put_uint(p, rejected);
  p = put_text(p, " errors=");
  p = put_uint(p, errors);
  p = put_text(p, " late=");
  p = put_uint(p, late);
  p = put_text(p, " no_position=");
  p = put_uint(p, noPosition);
  p = put_text(p, " busy_sample_max=");
  p = put_uint(p, busySampleMax);
  p = put_text(p, " busy_sample_total=");
  p = put_uint(p, busySampleTotal);
  p = put_text(p, " busy_other_max=");
  p = put_uint(p, busyOtherMax);
  p = put_text(p, " busy_other_total=");
  p = put_uint(p, busyOtherTotal);
  p = put_text(p, " tick_hz=");
  p = put_uint(p, platform_tick_hz());
  p = put_text(p, " stack_peak_bytes=");
  p = put_uint(p, platform_stack_peak());
  write_line(line, p);
  platform_exit(0);
}
