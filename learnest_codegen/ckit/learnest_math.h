/* learnest_math.h -- the one place where a build's math routines are chosen by precision.
 *
 * Included by learnest_kit.h (the kit's routines, on LEARNEST_REAL) and by the generated
 * model code <prefix>_model.c, whose calls of sin, cos, tanh, exp, sqrt, ... the generator
 * (codegen/casadi_c.py) renames to learnest_sin, learnest_cos, ... (LEARNEST_REAL =
 * casadi_real there). Each learnest_<name> runs in the build's precision: a float build calls
 * the float routine, a double build the double one (the choice is a constant sizeof test the
 * compiler folds away). docs/cortex_m.md states the parity bar per precision.
 *
 * Four routines are the kit's own, because they dominate the learned models' cost (a libm
 * call is 2-4x the instructions of these) and because libraries round them differently
 * (newlib and glibc differ in the last bit):
 *   learnest_tanh   both precisions: an odd series near 0, 1 - 2/(exp(2|x|) + 1) beyond
 *                   with the kit's own exp (double: a 64-entry table of 2^(j/64) and a
 *                   degree-5 polynomial); |error| <= 2.3e-16 (double), <= 3 ulp (float);
 *   learnest_sin, learnest_cos: Cody-Waite reduction by pi/2 in three parts and Taylor
 *                   polynomials; float: <= 2 ulp for |x| < 4096, double: |error| <= 2.3e-16
 *                   for |x| < 1e5 (beyond: the C library's double routine);
 *   learnest_exp (float): a 32-entry table of 2^(j/32) and a cubic polynomial, <= 2 ulp.
 * The float ones use + - * / and integer conversions only, so a float32 build computes the same bits
 * on every IEEE single machine (host x86-64 and the Cortex-M4F's FPv4-SP, -ffp-contract=off).
 * sqrt and fabs are exact in both libraries. The other routines are libm's (float ones in a
 * float build). tests/test_learnest_math.py checks them against numpy.
 */
#ifndef LEARNEST_MATH_H
#define LEARNEST_MATH_H

#include <math.h>
#include <string.h>

#ifndef LEARNEST_REAL
#error "learnest_math.h: define LEARNEST_REAL (double or float) before including it"
#endif

#if defined(__GNUC__) || defined(__clang__)
#define LEARNEST_MATH_FN static __attribute__((unused))
#else
#define LEARNEST_MATH_FN static
#endif

#define LEARNEST_MATH_IS_FLOAT (sizeof(LEARNEST_REAL) == sizeof(float))

/* 2^(j/64), j = 0..63, rounded to double, as E(value) for even j and O(value) for odd j.
 * The double table holds every entry; the float table 2^(j/32), j = 0..31, the even ones
 * rounded to float (for each of them the correctly rounded float 2^(j/32): rounding
 * through double changes none). */
#define LEARNEST_EXP2_64(E, O) \
  E(1.0) O(1.0108892860517005) E(1.0218971486541166) O(1.0330248790212284) E(1.0442737824274138) \
  O(1.0556451783605572) E(1.0671404006768237) O(1.0787607977571199) E(1.0905077326652577) \
  O(1.102382583307841) E(1.1143867425958924) O(1.1265216186082418) E(1.1387886347566916) \
  O(1.1511892299529827) E(1.1637248587775775) O(1.1763969916502812) E(1.189207115002721) \
  O(1.202156731452703) E(1.215247359980469) O(1.22848053610687) E(1.241857812073484) \
  O(1.255380757024691) E(1.2690509571917332) O(1.2828700160787783) E(1.2968395546510096) \
  O(1.3109612115247644) E(1.3252366431597413) O(1.339667524053303) E(1.3542555469368927) \
  O(1.3690024229745905) E(1.383909881963832) O(1.3989796725383112) E(1.4142135623730951) \
  O(1.42961333839197) E(1.4451808069770467) O(1.460917794180647) E(1.4768261459394993) \
  O(1.4929077282912648) E(1.5091644275934228) O(1.5255981507445384) E(1.5422108254079407) \
  O(1.559004400237837) E(1.5759808451078865) O(1.593142151342267) E(1.6104903319492543) \
  O(1.6280274218573478) E(1.645755478153965) O(1.6636765803267364) E(1.681792830507429) \
  O(1.7001063537185235) E(1.718619298122478) O(1.7373338352737062) E(1.7562521603732995) \
  O(1.7753764925265212) E(1.7947090750031072) O(1.8142521755003989) E(1.8340080864093424) \
  O(1.8539791250833855) E(1.8741676341103) O(1.8945759815869656) E(1.9152065613971474) \
  O(1.9360617934922943) E(1.9571441241754002) O(1.978456026387951)
#define LEARNEST_EXP2_DOUBLE_(v) v,
#define LEARNEST_EXP2_FLOAT_(v) (float)v,
#define LEARNEST_EXP2_SKIP_(v)
#if defined(__GNUC__) || defined(__clang__)
__attribute__((unused))
#endif
static const float learnest_exp2_32f_[32] = {LEARNEST_EXP2_64(LEARNEST_EXP2_FLOAT_, LEARNEST_EXP2_SKIP_)};
#if defined(__GNUC__) || defined(__clang__)
__attribute__((unused))
#endif
static const double learnest_exp2_64_[64] = {LEARNEST_EXP2_64(LEARNEST_EXP2_DOUBLE_, LEARNEST_EXP2_DOUBLE_)};

/* exp(y) in float for -87 < y < 88 and k = y 32/ln2 rounded to the nearest integer:
 * y = (32 m + j) ln2/32 + r, |r| <= ln2/64, cubic Taylor polynomial times 2^(j/32) 2^m. The
 * exponent's bits in unsigned arithmetic: 32 m = k - j exactly, and (k - j) / 32 + 127 (at
 * least 1 here) is (unsigned)(k - j) >> 5 plus 127 modulo 2^32, which a shift computes. */
LEARNEST_MATH_FN float learnest_expf_k_(float y, int k) {
  const float H = 0.02165985107421875f, L = 9.983182280848268e-07f;  /* ln2/32 in two parts */
  const int j = k & 31;
  const float r = (y - (float)k * H) - (float)k * L;
  const float p = 1.0f + r * (1.0f + r * (0.5f + r * 1.66666667e-1f));
  const unsigned int bits = (((unsigned int)(k - j) >> 5) + 127u) << 23;
  float scale;
  memcpy(&scale, &bits, sizeof scale);
  return learnest_exp2_32f_[j] * p * scale;
}

/* exp(y) in float for any y (own for -87 < y < 88: the same bits on every IEEE machine). */
LEARNEST_MATH_FN float learnest_expf_(float y) {
  if (!(y < 88.0f && y > -87.0f)) return (float)exp((double)y);  /* NaN, inf, extremes */
  return learnest_expf_k_(y, (int)(y * 46.16624130844683f + (y >= 0 ? 0.5f : -0.5f)));
}

/* learnest_expf_ for 0 <= y < 88 (tanh's argument), without its range test and sign: the same
 * bits. */
LEARNEST_MATH_FN float learnest_expf_pos_(float y) {
  return learnest_expf_k_(y, (int)(y * 46.16624130844683f + 0.5f));
}

/* tanh(x) in type T, one body for both precisions: the odd series poly(a, a2) for |x| < small,
 * 1 - 2/(exp(2|x|) + 1) up to big (the kit's exp in T), 1 beyond (tanh(big) rounds to 1 in T). */
#define LEARNEST_TANH_(name, T, exp_, big, small, poly)          \
  LEARNEST_MATH_FN T name(T x) {                                 \
    T a = x < 0 ? -x : x, t;                                     \
    if (x != x) return x;                                        \
    if (a >= (big)) {                                            \
      t = (T)1;                                                  \
    } else if (a < (small)) {                                    \
      T a2 = a * a;                                              \
      t = poly(a, a2);                                           \
    } else {                                                     \
      t = (T)1 - (T)2 / (exp_((T)2 * a) + (T)1);                 \
    }                                                            \
    return x < 0 ? -t : t;                                       \
  }

#define LEARNEST_TANHF_POLY_(a, a2) \
  (a + a * a2 * (-3.33333333e-1f + a2 * (1.33333333e-1f + a2 * (-5.39682540e-2f \
   + a2 * (2.18694885e-2f + a2 * -8.86323552e-3f)))))
LEARNEST_TANH_(learnest_tanhf_, float, learnest_expf_pos_, 9.0f, 0.35f, LEARNEST_TANHF_POLY_)

/* exp(y) in double for 0 <= y <= 700: y = (64 m + j) ln2/64 + r, |r| <= ln2/128, degree-5
 * Taylor polynomial times 2^(j/64) 2^m (about 1 ulp). */
LEARNEST_MATH_FN double learnest_expd_(double y) {
  const double H = 0.010830417275428772, L = 7.420820373486988e-09;  /* ln2/64 in two parts */
  int k = (int)(y * 92.33248261689366 + 0.5);
  double r = (y - (double)k * H) - (double)k * L, p, scale;
  unsigned long long bits = (unsigned long long)((k >> 6) + 1023) << 52;
  memcpy(&scale, &bits, sizeof scale);
  p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6 + r * (1.0 / 24 + r * (1.0 / 120)))));
  return learnest_exp2_64_[k & 63] * p * scale;
}

#define LEARNEST_TANHD_POLY_(a, a2) \
  (a + a * a2 * (-1.0 / 3 + a2 * (2.0 / 15 + a2 * (-17.0 / 315 + a2 * (62.0 / 2835 \
   + a2 * (-1382.0 / 155925 + a2 * (21844.0 / 6081075 + a2 * (-929569.0 / 638512875))))))))
LEARNEST_TANH_(learnest_tanhd_, double, learnest_expd_, 22.0, 0.125, LEARNEST_TANHD_POLY_)

/* sin (c = 0) or cos (c = 1) in float: x = q pi/2 + r, |r| <= pi/4. */
LEARNEST_MATH_FN float learnest_sincosf_(float x, int c) {
  const float P1 = 1.5703125f, P2 = 4.837512969970703e-04f, P3 = 7.549790126404332e-08f;
  float r, r2, s, co;
  int q;
  if (!(x < 4096.0f && x > -4096.0f)) return (float)(c ? cos((double)x) : sin((double)x));
  q = (int)(x * 6.36619772e-1f + (x >= 0 ? 0.5f : -0.5f));
  r = ((x - (float)q * P1) - (float)q * P2) - (float)q * P3;
  r2 = r * r;
  s = r + r * r2 * (-1.66666667e-1f + r2 * (8.33333333e-3f + r2 * (-1.98412698e-4f
      + r2 * 2.75573192e-6f)));
  co = 1.0f + r2 * (-0.5f + r2 * (4.16666667e-2f + r2 * (-1.38888889e-3f
       + r2 * (2.48015873e-5f + r2 * -2.75573192e-7f))));
  switch ((q + c) & 3) {
    case 0: return s;
    case 1: return co;
    case 2: return -s;
    default: return -co;
  }
}

/* sin (c = 0) or cos (c = 1) in double: x = q pi/2 + r, |r| <= pi/4 (three-part pi/2, each
 * part of 32 bits so q * part is exact), Taylor polynomials to r^15 / r^16. */
LEARNEST_MATH_FN double learnest_sincosd_(double x, int c) {
  const double P1 = 1.5707963267341256, P2 = 6.077100506303966e-11, P3 = 2.0222662487959506e-21;
  double r, r2, v;
  int q;
  if (!(x < 1e5 && x > -1e5)) return c ? cos(x) : sin(x);  /* NaN, inf, large */
  q = (int)(x * 0.6366197723675814 + (x >= 0 ? 0.5 : -0.5));
  r = ((x - (double)q * P1) - (double)q * P2) - (double)q * P3;
  r2 = r * r;
  if ((q + c) & 1) {
    v = 1.0 - 0.5 * r2 + r2 * r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320
        + r2 * (-1.0 / 3628800 + r2 * (1.0 / 479001600 + r2 * (-1.0 / 87178291200.0
        + r2 * (1.0 / 20922789888000.0)))))));
  } else {
    v = r + r * r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880
        + r2 * (-1.0 / 39916800 + r2 * (1.0 / 6227020800.0 + r2 * (-1.0 / 1307674368000.0)))))));
  }
  return ((q + c) & 2) ? -v : v;
}

/* learnest_<name>(x): the routine in the build's precision. */
#define LEARNEST_MATH_1(name, fl, db)                                                        \
  LEARNEST_MATH_FN LEARNEST_REAL learnest_##name(LEARNEST_REAL x) {                          \
    return LEARNEST_MATH_IS_FLOAT ? (LEARNEST_REAL)fl((float)x) : (LEARNEST_REAL)db((double)x); \
  }
#define LEARNEST_MATH_2(name, fl, db)                                                   \
  LEARNEST_MATH_FN LEARNEST_REAL learnest_##name(LEARNEST_REAL x, LEARNEST_REAL y) {    \
    return LEARNEST_MATH_IS_FLOAT ? (LEARNEST_REAL)fl((float)x, (float)y)               \
                                  : (LEARNEST_REAL)db((double)x, (double)y);            \
  }

LEARNEST_MATH_FN float learnest_sinf_(float x) { return learnest_sincosf_(x, 0); }
LEARNEST_MATH_FN float learnest_cosf_(float x) { return learnest_sincosf_(x, 1); }
LEARNEST_MATH_FN double learnest_sind_(double x) { return learnest_sincosd_(x, 0); }
LEARNEST_MATH_FN double learnest_cosd_(double x) { return learnest_sincosd_(x, 1); }

LEARNEST_MATH_1(tanh, learnest_tanhf_, learnest_tanhd_)
LEARNEST_MATH_1(sin, learnest_sinf_, learnest_sind_)
LEARNEST_MATH_1(cos, learnest_cosf_, learnest_cosd_)
LEARNEST_MATH_1(exp, learnest_expf_, exp)

/* The C library's routines: learnest_<name> calls <name>f in a float build, <name> in a double
 * one. */
#define LEARNEST_LIBM_1(X) X(sqrt) X(fabs) X(tan) X(asin) X(acos) X(atan) X(sinh) X(cosh) \
  X(asinh) X(acosh) X(atanh) X(log) X(log1p) X(expm1) X(floor) X(ceil) X(erf)
#define LEARNEST_LIBM_2(X) X(atan2) X(pow) X(fmod) X(fmin) X(fmax) X(hypot) X(copysign)
#define LEARNEST_LIBM_1_(name) LEARNEST_MATH_1(name, name##f, name)
#define LEARNEST_LIBM_2_(name) LEARNEST_MATH_2(name, name##f, name)
LEARNEST_LIBM_1(LEARNEST_LIBM_1_)
LEARNEST_LIBM_2(LEARNEST_LIBM_2_)

/* The kit's names. */
#define LEARNEST_SQRT(x) learnest_sqrt(x)
#define LEARNEST_FABS(x) learnest_fabs(x)

#endif /* LEARNEST_MATH_H */
