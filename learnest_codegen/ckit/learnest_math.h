/* learnest_math.h -- the one place where a build's math routines are chosen by precision.
 *
 * Included by learnest_kit.h (the kit's routines, on LEARNEST_REAL) and by the generated
 * model code <prefix>_model.c (codegen/casadi_c.py inserts it after CasADi's definitions,
 * with LEARNEST_REAL = casadi_real). Today every build calls the double routines: a float
 * argument widens exactly and the result rounds back, which keeps float32 builds
 * bit-identical across C libraries (docs/cortex_m.md). A float build that should call
 * sqrtf, sinf, tanhf & co. changes this file only: the kit's macros below, and for the model
 * code a mapping of CasADi's names (sin, cos, tanh, exp, sqrt, fabs) after <math.h>.
 */
#ifndef LEARNEST_MATH_H
#define LEARNEST_MATH_H

#include <math.h>

#define LEARNEST_SQRT(x) ((LEARNEST_REAL)sqrt((double)(x)))
#define LEARNEST_FABS(x) ((LEARNEST_REAL)fabs((double)(x)))

#endif /* LEARNEST_MATH_H */
