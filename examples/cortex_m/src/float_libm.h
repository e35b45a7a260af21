/* float_libm.h: single-precision libm for a float32 build's CasADi code (an experiment).
 *
 * CasADi 3.8 writes sin(), cos(), tanh(), exp(), sqrt() and fabs() for casadi_real = float too,
 * so each such call widens to double, runs the double routine (libgcc soft-float on a
 * Cortex-M4F) and rounds back. Included first (make CASADI_CFLAGS="-include src/float_libm.h"),
 * this header maps them to the float routines; <math.h>'s guard makes the file's own include
 * a no-op. Results then depend on each libm's float routines (docs/cortex_m.md). */
#ifndef FLOAT_LIBM_H
#define FLOAT_LIBM_H

#include <math.h>

#define sin sinf
#define cos cosf
#define tanh tanhf
#define exp expf
#define sqrt sqrtf
#define fabs fabsf

#endif /* FLOAT_LIBM_H */
