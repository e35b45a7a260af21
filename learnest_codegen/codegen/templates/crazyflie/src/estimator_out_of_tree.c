/* estimator_out_of_tree.c -- a learnest_codegen estimator as the Crazyflie's out-of-tree state
 * estimator (copied by learnest-compile --target crazyflie; docs/guide/crazyflie.md).
 *
 * The estimator is the generated folder's (learnest_app.h names it); this file only adapts it
 * to the firmware, the way the firmware's own Kalman estimator is arranged:
 *
 * - The stabilizer loop (1 kHz) calls estimatorOutOfTree(): it copies the latest estimate into
 *   state_t, counts a sample due every 1000 / APP_SAMPLE_RATE_HZ ticks and wakes the app task.
 *   It never waits for the estimator.
 * - The app task (appMain) drains the firmware's measurement queue: the gyroscope carries the
 *   attitude forward (math3d's quat_gyro_update), a motion-capture pose replaces it and gives
 *   the position, a position alone gives the position, the accelerometer its latest sample
 *   (the firmware low-passes it already). At each sample due it forms
 *     y = [p, R(q) (g acc) - g e3]   (position [m], world acceleration [m/s^2]),
 *     u = [R(q) e3 pwm, vbat]        (thrust along the body z axis as a fraction of full PWM,
 *                                     battery voltage [V]),
 *   marks an output missing (valid = 0) when nothing new arrived for it in that period (the
 *   acceleration also before the first pose: it needs the attitude), and steps the estimator
 *   with the input of the previous sample (the input applied since then). The estimator starts
 *   at the first sample with a position, from x0 = [p, 0, a] (a = 0 when not measured) and the
 *   tuned covariances of the generated header.
 * - The estimate fills state_t: position, velocity, acceleration (in g, as the firmware's
 *   estimators give it), and the attitude above (roll, pitch, yaw in degrees with the legacy
 *   inverted pitch, and the quaternion).
 *
 * Parameters (group learnest): reset (write 1: start again at the next sample with a
 * position), gateThr (the innovation gate's chi-square threshold; 0 disables it). Logs (group
 * learnest): status of the last step, steps, rejected outputs, errors, late samples (taken as
 * predictions because the estimator task fell behind), samples without a position, the last step's
 * duration [us] and the measured world acceleration.
 */
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

#include "FreeRTOS.h"
#include "semphr.h"
#include "task.h"

#include "app.h"
#include "estimator.h"
#include "log.h"
#include "math3d.h"
#include "motors.h"
#include "param.h"
#include "pm.h"
#include "usec_time.h"

#define DEBUG_MODULE "LEARNEST"
#include "debug.h"

#include "learnest_app.h"

#define PWM_FULL 65535.0f
#define IMU_DT_S (1.0f / RATE_MAIN_LOOP) /* one gyroscope sample per stabilizer tick [s] */

/* The estimator: its memory is this static buffer (RAM), no heap. */
static unsigned char workspace[APP_WORKSPACE_BYTES];
static app_estimator_t* estimator;
static const app_real defaultP0[APP_NX * APP_NX] = APP_DEFAULT_P0;
static const app_real defaultQ[APP_NX * APP_NX] = APP_DEFAULT_Q;
static const app_real defaultR[APP_NY * APP_NY] = APP_DEFAULT_R;

/* Shared by the stabilizer loop and the estimator task, under dataMutex. */
static state_t taskState;
static uint32_t samplesDue;
static SemaphoreHandle_t runTaskSemaphore;
static StaticSemaphore_t runTaskSemaphoreBuffer;
static SemaphoreHandle_t dataMutex;
static StaticSemaphore_t dataMutexBuffer;
static bool isInit = false;

/* The estimator task's view of the sensors since the last sample. */
static struct quat attitude = {.x = 0.0f, .y = 0.0f, .z = 0.0f, .w = 1.0f}; /* body to world */
static bool haveAttitude = false; /* a pose has set it since the start */
static struct vec position, accG; /* [m], [g] */
static bool freshPosition = false, freshAcc = false;

/* The last sample given to the estimator (also logged). */
static struct {
  app_real u[APP_NU];
  app_real y[APP_NY];
  unsigned char valid[APP_NY];
} sample;
static app_real uPrevious[APP_NU];
static bool started = false;

/* Parameters. */
static uint8_t resetRequest = 0;
static float gateThreshold = (float)APP_DEFAULT_GATE_THRESHOLD;
static float gateApplied = (float)APP_DEFAULT_GATE_THRESHOLD;

/* Logs. */
static int8_t lastStatus = 0;
static uint32_t steps = 0, rejected = 0, errors = 0, late = 0, noPosition = 0, stepUs = 0;
static uint32_t rejectedBeforeReset = 0;

static void startEstimator(void) {
  int status = APP_INIT_DEFAULT(workspace, sizeof workspace, &estimator);
  DEBUG_PRINT("%s: %s\n", status == LEARNEST_OK ? "ready" : "init failed", APP_FINGERPRINT());
  gateApplied = (float)APP_DEFAULT_GATE_THRESHOLD;
  started = false;
}

static void processMeasurements(void) {
  measurement_t m;
  while (estimatorDequeue(&m)) {
    switch (m.type) {
      case MeasurementTypeGyroscope: {
        const Axis3f* g = &m.data.gyroscope.gyro; /* [deg/s] */
        attitude = qnormalize(quat_gyro_update(
            attitude, mkvec(radians(g->x), radians(g->y), radians(g->z)), IMU_DT_S));
        break;
      }
      case MeasurementTypeAcceleration:
        accG = mkvec(m.data.acceleration.acc.x, m.data.acceleration.acc.y, m.data.acceleration.acc.z);
        freshAcc = true;
        break;
      case MeasurementTypePose:
        position = mkvec(m.data.pose.x, m.data.pose.y, m.data.pose.z);
        attitude = mkquat(m.data.pose.quat.x, m.data.pose.quat.y, m.data.pose.quat.z, m.data.pose.quat.w);
        haveAttitude = true;
        freshPosition = true;
        break;
      case MeasurementTypePosition:
        position = mkvec(m.data.position.x, m.data.position.y, m.data.position.z);
        freshPosition = true;
        break;
      default:
        break;
    }
  }
}

/* u, y and valid of the sample due now, from the sensors since the previous one. */
static void formSample(void) {
  const float pwm = (float)((uint32_t)motorsGetRatio(0) + motorsGetRatio(1) + motorsGetRatio(2)
                            + motorsGetRatio(3)) / (4.0f * PWM_FULL);
  const struct vec thrust = vscl(pwm, qvrot(attitude, mkvec(0.0f, 0.0f, 1.0f)));
  sample.u[APP_INPUT_T + 0] = thrust.x;
  sample.u[APP_INPUT_T + 1] = thrust.y;
  sample.u[APP_INPUT_T + 2] = thrust.z;
  sample.u[APP_INPUT_VBAT] = pmGetBatteryVoltage();
  memset(sample.valid, 0, sizeof sample.valid);
  if (freshPosition) {
    sample.y[APP_OUTPUT_P + 0] = position.x;
    sample.y[APP_OUTPUT_P + 1] = position.y;
    sample.y[APP_OUTPUT_P + 2] = position.z;
    memset(&sample.valid[APP_OUTPUT_P], 1, 3);
  }
  if (freshAcc && haveAttitude) {
    const struct vec a = vsub(qvrot(attitude, vscl(APP_GRAVITY, accG)), mkvec(0.0f, 0.0f, APP_GRAVITY));
    sample.y[APP_OUTPUT_A + 0] = a.x;
    sample.y[APP_OUTPUT_A + 1] = a.y;
    sample.y[APP_OUTPUT_A + 2] = a.z;
    memset(&sample.valid[APP_OUTPUT_A], 1, 3);
  }
  freshPosition = freshAcc = false;
}

/* Start from the sample's position (at rest, with its acceleration when measured). */
static int restart(void) {
  app_real x0[APP_NX] = {0};
  int i;
  for (i = 0; i < 3; ++i) {
    x0[APP_STATE_P + i] = sample.y[APP_OUTPUT_P + i];
    x0[APP_STATE_A + i] = sample.valid[APP_OUTPUT_A + i] ? sample.y[APP_OUTPUT_A + i] : 0.0f;
  }
  rejectedBeforeReset = rejected;
  return APP_RESET(estimator, x0, defaultP0, defaultQ, defaultR);
}

static void applyParameters(void) {
  if (resetRequest) {
    resetRequest = 0;
    started = false;
  }
  if (gateThreshold != gateApplied) {
    if (APP_SET_GATE(estimator, gateThreshold, APP_DEFAULT_GATE_RECOVER_AFTER,
                     (app_real)APP_DEFAULT_GATE_INFLATION) == LEARNEST_OK) {
      gateApplied = gateThreshold;
    } else {
      gateThreshold = gateApplied; /* out of range: the parameter reads back what is in force */
    }
  }
}

/* One sample: the late ones as predictions, then this one with its measurements. */
static void takeSample(uint32_t due) {
  const uint64_t start = usecTimestamp();
  int status = LEARNEST_OK;
  formSample();
  if (!started) {
    if (!sample.valid[APP_OUTPUT_P]) {
      ++noPosition;
      return;
    }
    status = restart();
    if (status >= 0) {
      started = true;
      status = APP_STEP(estimator, sample.u, sample.y, sample.valid);
    }
  } else {
    for (; due > 1 && status >= 0; --due, ++late) status = APP_PREDICT(estimator, uPrevious);
    if (status >= 0) status = APP_STEP(estimator, uPrevious, sample.y, sample.valid);
    if (!sample.valid[APP_OUTPUT_P]) ++noPosition;
  }
  memcpy(uPrevious, sample.u, sizeof uPrevious);
  lastStatus = (int8_t)status;
  if (status < 0) {
    ++errors;
    started = false; /* the estimator is as before the call; start again from the next position */
  } else {
    ++steps;
    rejected = rejectedBeforeReset + (uint32_t)APP_REJECTIONS(estimator);
  }
  stepUs = (uint32_t)(usecTimestamp() - start);
}

static void publish(void) {
  app_real x[APP_NX];
  const struct vec rpy = quat2rpy(attitude);
  const bool estimate = started && APP_GET_STATE(estimator, x) == LEARNEST_OK;
  xSemaphoreTake(dataMutex, portMAX_DELAY);
  if (estimate) {
    taskState.position.x = x[APP_STATE_P + 0];
    taskState.position.y = x[APP_STATE_P + 1];
    taskState.position.z = x[APP_STATE_P + 2];
    taskState.velocity.x = x[APP_STATE_V + 0];
    taskState.velocity.y = x[APP_STATE_V + 1];
    taskState.velocity.z = x[APP_STATE_V + 2];
    taskState.acc.x = x[APP_STATE_A + 0] / APP_GRAVITY;
    taskState.acc.y = x[APP_STATE_A + 1] / APP_GRAVITY;
    taskState.acc.z = x[APP_STATE_A + 2] / APP_GRAVITY;
  }
  taskState.attitude.roll = degrees(rpy.x);
  taskState.attitude.pitch = -degrees(rpy.y); /* the legacy CF2 body frame */
  taskState.attitude.yaw = degrees(rpy.z);
  taskState.attitudeQuaternion.x = attitude.x;
  taskState.attitudeQuaternion.y = attitude.y;
  taskState.attitudeQuaternion.z = attitude.z;
  taskState.attitudeQuaternion.w = attitude.w;
  xSemaphoreGive(dataMutex);
}

/* One pass of the estimator task: woken by the stabilizer loop once per tick. */
static void taskRound(void) {
  uint32_t due;
  xSemaphoreTake(runTaskSemaphore, portMAX_DELAY);
  xSemaphoreTake(dataMutex, portMAX_DELAY);
  due = samplesDue;
  samplesDue = 0;
  xSemaphoreGive(dataMutex);
  if (!estimator) startEstimator();
  processMeasurements();
  if (due) {
    applyParameters();
    takeSample(due);
  }
  publish();
}

void appMain(void) {
  while (!isInit) vTaskDelay(M2T(10));
  for (;;) taskRound();
}

void estimatorOutOfTreeInit(void) {
  if (!isInit) {
    runTaskSemaphore = xSemaphoreCreateBinaryStatic(&runTaskSemaphoreBuffer);
    dataMutex = xSemaphoreCreateMutexStatic(&dataMutexBuffer);
    isInit = true;
  }
  resetRequest = 1;
}

bool estimatorOutOfTreeTest(void) { return isInit; }

void estimatorOutOfTree(state_t* state, const stabilizerStep_t stabilizerStep) {
  /* Called by the stabilizer loop: copy the estimate and return at once. */
  xSemaphoreTake(dataMutex, portMAX_DELAY);
  memcpy(state, &taskState, sizeof(state_t));
  if (RATE_DO_EXECUTE(APP_SAMPLE_RATE_HZ, stabilizerStep)) ++samplesDue;
  xSemaphoreGive(dataMutex);
  xSemaphoreGive(runTaskSemaphore);
}

PARAM_GROUP_START(learnest)
PARAM_ADD(PARAM_UINT8, reset, &resetRequest)
PARAM_ADD(PARAM_FLOAT, gateThr, &gateThreshold)
PARAM_GROUP_STOP(learnest)

LOG_GROUP_START(learnest)
LOG_ADD(LOG_INT8, status, &lastStatus)
LOG_ADD(LOG_UINT32, steps, &steps)
LOG_ADD(LOG_UINT32, rejected, &rejected)
LOG_ADD(LOG_UINT32, errors, &errors)
LOG_ADD(LOG_UINT32, late, &late)
LOG_ADD(LOG_UINT32, noPos, &noPosition)
LOG_ADD(LOG_UINT32, stepUs, &stepUs)
LOG_ADD(LOG_FLOAT, ax, &sample.y[APP_OUTPUT_A + 0])
LOG_ADD(LOG_FLOAT, ay, &sample.y[APP_OUTPUT_A + 1])
LOG_ADD(LOG_FLOAT, az, &sample.y[APP_OUTPUT_A + 2])
LOG_GROUP_STOP(learnest)
