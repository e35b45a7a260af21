/* learnest_simd.h -- lane-parallel forms of the kit's math routines, for a model evaluated on
 * several points at once (the UKF's sigma points, the MHEs' stages).
 *
 * A batch of 4 (double) or 8 (float) points is one GCC vector per quantity (lane i = point i):
 * learnest_v4d (4 doubles) or learnest_v8f (8 floats), 32 bytes. + - * / on vectors are the
 * same IEEE operations as on scalars, lane by lane (the kit builds with -ffp-contract=off, so
 * no lane is contracted into an FMA), and each routine here computes, lane by lane, exactly
 * the operations of its scalar routine in learnest_math.h (branches become masks: both sides
 * are computed and each lane keeps its own; a rare side, such as an argument beyond the
 * reduction range, runs the scalar routine on each lane). A batched model therefore returns
 * the bits of the scalar model on every point (tests/test_simd.py compares them, and
 * tests/test_ckit.py the kit's batched paths over a hand-written model, tests/ckit/kit_lanes.h).
 *
 * Available (LEARNEST_SIMD 1) with GCC compiling C for x86-64, where SSE2 is the
 * baseline: the code is built twice (target_clones), for AVX2 (one instruction a vector) and
 * for the baseline (two SSE2 instructions a vector), and the loader picks the one the CPU
 * runs. Elsewhere (the Cortex-M4F has no double or float SIMD; clang, which refuses 32-byte
 * vectors by value without AVX; C++) LEARNEST_SIMD is 0 and the estimators call the scalar
 * model once per point.
 */
#ifndef LEARNEST_SIMD_H
#define LEARNEST_SIMD_H

#include "learnest_math.h"

#if defined(__GNUC__) && defined(__x86_64__) && defined(__SSE2__) \
    && !defined(__cplusplus) && !defined(__clang__) && !defined(LEARNEST_NO_SIMD)
#define LEARNEST_SIMD 1
#else
#define LEARNEST_SIMD 0
#endif

#if LEARNEST_SIMD
/* The vectors are only passed between always-inlined routines (never through a call), so
 * the ABI of 32-byte vectors without AVX, which GCC warns about, does not arise. The pragma
 * silences the warning; GCC's accompanying note ("the ABI for passing parameters with 32-byte
 * alignment has changed in GCC 4.6") ignores it, and the package's flags (toolchain.CFLAGS,
 * the folder's build fragment) carry -Wno-psabi for it. */
#pragma GCC diagnostic ignored "-Wpsabi"

#define LEARNEST_SIMD_FN static inline __attribute__((always_inline, unused))
/* A batched model function: built for AVX2 and for the x86-64 baseline, chosen at load. */
#define LEARNEST_SIMD_BATCH __attribute__((target_clones("avx2", "default")))

typedef double learnest_v4d __attribute__((vector_size(32)));
typedef long long learnest_v4l __attribute__((vector_size(32)));
typedef unsigned long long learnest_v4u __attribute__((vector_size(32)));
typedef float learnest_v8f __attribute__((vector_size(32)));
typedef int learnest_v8i __attribute__((vector_size(32)));

/* Lane by lane m ? a : b, m a comparison's result (all ones or all zeros a lane). */
#define LEARNEST_VSEL_D(m, a, b) ((learnest_v4d)(((m) & (learnest_v4l)(a)) | (~(m) & (learnest_v4l)(b))))
#define LEARNEST_VSEL_F(m, a, b) ((learnest_v8f)(((m) & (learnest_v8i)(a)) | (~(m) & (learnest_v8i)(b))))

LEARNEST_SIMD_FN learnest_v4d learnest_vdup_d(double c) {
  learnest_v4d v = {c, c, c, c};
  return v;
}

LEARNEST_SIMD_FN learnest_v8f learnest_vdup_f(float c) {
  learnest_v8f v = {c, c, c, c, c, c, c, c};
  return v;
}

LEARNEST_SIMD_FN int learnest_vany_d(learnest_v4l m) { return (m[0] | m[1] | m[2] | m[3]) != 0; }

LEARNEST_SIMD_FN int learnest_vany_f(learnest_v8i m) {
  return (m[0] | m[1] | m[2] | m[3] | m[4] | m[5] | m[6] | m[7]) != 0;
}

/* floor(s) for 0 <= s < 2^51 (double) / 2^22 (float), exactly: s + 2^52 - 2^52 rounds s to
 * an integer, one less where that rounded up. */
LEARNEST_SIMD_FN learnest_v4d learnest_vfloor_d(learnest_v4d s) {
  learnest_v4d t = (s + 4503599627370496.0) - 4503599627370496.0;
  return t - LEARNEST_VSEL_D(t > s, learnest_vdup_d(1.0), learnest_vdup_d(0.0));
}

LEARNEST_SIMD_FN learnest_v8f learnest_vfloor_f(learnest_v8f s) {
  learnest_v8f t = (s + 8388608.0f) - 8388608.0f;
  return t - LEARNEST_VSEL_F(t > s, learnest_vdup_f(1.0f), learnest_vdup_f(0.0f));
}

/* (int)s, C's truncation, as a double / float holding the integer (+0 for 0, as (double)(int)
 * gives), for |s| < 2^51 / 2^22. */
LEARNEST_SIMD_FN learnest_v4d learnest_vtrunc_d(learnest_v4d s) {
  learnest_v4l neg = s < 0;
  learnest_v4d f = learnest_vfloor_d(LEARNEST_VSEL_D(neg, -s, s));
  return LEARNEST_VSEL_D(neg, -f, f) + 0.0;
}

LEARNEST_SIMD_FN learnest_v8f learnest_vtrunc_f(learnest_v8f s) {
  learnest_v8i neg = s < 0;
  learnest_v8f f = learnest_vfloor_f(LEARNEST_VSEL_F(neg, -s, s));
  return LEARNEST_VSEL_F(neg, -f, f) + 0.0f;
}

/* The integer an integral double / float t (|t| < 2^51 / 2^22) holds, as an integer lane. */
LEARNEST_SIMD_FN learnest_v4l learnest_vint_d(learnest_v4d t) {
  return (learnest_v4l)(t + 6755399441055744.0) - 0x4338000000000000LL;
}

LEARNEST_SIMD_FN learnest_v8i learnest_vint_f(learnest_v8f t) {
  return (learnest_v8i)(t + 12582912.0f) - 0x4B400000;
}

/* learnest_tanhd_ lane by lane (its exp path is learnest_expd_ on y = 2|x|). */
LEARNEST_SIMD_FN learnest_v4d learnest_vtanh_d(learnest_v4d x) {
  const double H = 0.010830417275428772, L = 7.420820373486988e-09;
  learnest_v4l neg = x < 0, nan = x != x;
  learnest_v4d a = LEARNEST_VSEL_D(neg, -x, x), y, k, r, p, scale, e, t;
  learnest_v4l big = a >= 22.0, small = a < 0.125, kk, bits;
  /* The exp path on every lane (y = 1 where another side is taken: no overflow, no NaN). */
  y = LEARNEST_VSEL_D(big | small | nan, learnest_vdup_d(1.0), 2.0 * a);
  k = learnest_vfloor_d(y * 92.33248261689366 + 0.5);
  kk = learnest_vint_d(k);
  r = (y - k * H) - k * L;
  bits = (learnest_v4l)((((learnest_v4u)kk >> 6) + 1023) << 52);
  scale = (learnest_v4d)bits;
  p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6 + r * (1.0 / 24 + r * (1.0 / 120)))));
  e[0] = learnest_exp2_64_[kk[0] & 63], e[1] = learnest_exp2_64_[kk[1] & 63];
  e[2] = learnest_exp2_64_[kk[2] & 63], e[3] = learnest_exp2_64_[kk[3] & 63];
  t = 1.0 - 2.0 / (e * p * scale + 1.0);
  t = LEARNEST_VSEL_D(big, learnest_vdup_d(1.0), t);
  if (learnest_vany_d(small)) {
    learnest_v4d a2 = a * a;
    learnest_v4d s = a + a * a2 * (-1.0 / 3 + a2 * (2.0 / 15 + a2 * (-17.0 / 315 + a2 * (62.0 / 2835
        + a2 * (-1382.0 / 155925 + a2 * (21844.0 / 6081075 + a2 * (-929569.0 / 638512875)))))));
    t = LEARNEST_VSEL_D(small, s, t);
  }
  t = LEARNEST_VSEL_D(neg, -t, t);
  return LEARNEST_VSEL_D(nan, x, t);
}

/* learnest_tanhf_ lane by lane (its exp path is learnest_expf_ on y = 2|x|). */
LEARNEST_SIMD_FN learnest_v8f learnest_vtanh_f(learnest_v8f x) {
  const float H = 0.02165985107421875f, L = 9.983182280848268e-07f;
  learnest_v8i neg = x < 0, nan = x != x;
  learnest_v8f a = LEARNEST_VSEL_F(neg, -x, x), y, k, r, p, scale, e, t;
  learnest_v8i big = a >= 9.0f, small = a < 0.35f, kk, j;
  int i;
  y = LEARNEST_VSEL_F(big | small | nan, learnest_vdup_f(1.0f), 2.0f * a);
  k = learnest_vfloor_f(y * 46.16624130844683f + 0.5f);
  kk = learnest_vint_f(k);
  j = kk & 31;
  r = (y - k * H) - k * L;
  p = 1.0f + r * (1.0f + r * (0.5f + r * 1.66666667e-1f));
  scale = (learnest_v8f)((((kk - j) >> 5) + 127) << 23);  /* (k - j) / 32, exact */
  for (i = 0; i < 8; ++i) e[i] = learnest_exp2_32f_[j[i]];
  t = 1.0f - 2.0f / (e * p * scale + 1.0f);
  t = LEARNEST_VSEL_F(big, learnest_vdup_f(1.0f), t);
  if (learnest_vany_f(small)) {
    learnest_v8f a2 = a * a;
    learnest_v8f s = a + a * a2 * (-3.33333333e-1f + a2 * (1.33333333e-1f + a2 * (-5.39682540e-2f
        + a2 * (2.18694885e-2f + a2 * -8.86323552e-3f))));
    t = LEARNEST_VSEL_F(small, s, t);
  }
  t = LEARNEST_VSEL_F(neg, -t, t);
  return LEARNEST_VSEL_F(nan, x, t);
}

/* learnest_sincosd_(x, c) lane by lane (c = 0: sin, 1: cos). */
LEARNEST_SIMD_FN learnest_v4d learnest_vsincos_d(learnest_v4d x, int c) {
  const double P1 = 1.5707963267341256, P2 = 6.077100506303966e-11, P3 = 2.0222662487959506e-21;
  learnest_v4d q, r, r2, vs, vc, v;
  learnest_v4l qc, inside = (x < 1e5) & (x > -1e5);
  int i;
  if (!((inside[0] & inside[1] & inside[2] & inside[3]) != 0)) {
    for (i = 0; i < 4; ++i) v[i] = learnest_sincosd_(x[i], c);
    return v;
  }
  q = learnest_vtrunc_d(x * 0.6366197723675814
                        + LEARNEST_VSEL_D(x >= 0, learnest_vdup_d(0.5), learnest_vdup_d(-0.5)));
  qc = learnest_vint_d(q) + c;
  r = ((x - q * P1) - q * P2) - q * P3;
  r2 = r * r;
  vc = 1.0 - 0.5 * r2 + r2 * r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320
      + r2 * (-1.0 / 3628800 + r2 * (1.0 / 479001600 + r2 * (-1.0 / 87178291200.0
      + r2 * (1.0 / 20922789888000.0)))))));
  vs = r + r * r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880
      + r2 * (-1.0 / 39916800 + r2 * (1.0 / 6227020800.0 + r2 * (-1.0 / 1307674368000.0)))))));
  v = LEARNEST_VSEL_D((qc & 1) != 0, vc, vs);
  return LEARNEST_VSEL_D((qc & 2) != 0, -v, v);
}

/* learnest_sincosf_(x, c) lane by lane. */
LEARNEST_SIMD_FN learnest_v8f learnest_vsincos_f(learnest_v8f x, int c) {
  const float P1 = 1.5703125f, P2 = 4.837512969970703e-04f, P3 = 7.549790126404332e-08f;
  learnest_v8f q, r, r2, s, co, v;
  learnest_v8i qc, inside = (x < 4096.0f) & (x > -4096.0f);
  int i, all = 1;
  for (i = 0; i < 8; ++i) all &= inside[i] != 0;
  if (!all) {
    for (i = 0; i < 8; ++i) v[i] = learnest_sincosf_(x[i], c);
    return v;
  }
  q = learnest_vtrunc_f(x * 6.36619772e-1f
                        + LEARNEST_VSEL_F(x >= 0, learnest_vdup_f(0.5f), learnest_vdup_f(-0.5f)));
  qc = learnest_vint_f(q) + c;
  r = ((x - q * P1) - q * P2) - q * P3;
  r2 = r * r;
  s = r + r * r2 * (-1.66666667e-1f + r2 * (8.33333333e-3f + r2 * (-1.98412698e-4f
      + r2 * 2.75573192e-6f)));
  co = 1.0f + r2 * (-0.5f + r2 * (4.16666667e-2f + r2 * (-1.38888889e-3f
       + r2 * (2.48015873e-5f + r2 * -2.75573192e-7f))));
  v = LEARNEST_VSEL_F((qc & 1) != 0, co, s);
  return LEARNEST_VSEL_F((qc & 2) != 0, -v, v);
}

LEARNEST_SIMD_FN learnest_v4d learnest_vsin_d(learnest_v4d x) { return learnest_vsincos_d(x, 0); }
LEARNEST_SIMD_FN learnest_v4d learnest_vcos_d(learnest_v4d x) { return learnest_vsincos_d(x, 1); }
LEARNEST_SIMD_FN learnest_v8f learnest_vsin_f(learnest_v8f x) { return learnest_vsincos_f(x, 0); }
LEARNEST_SIMD_FN learnest_v8f learnest_vcos_f(learnest_v8f x) { return learnest_vsincos_f(x, 1); }
LEARNEST_SIMD_FN learnest_v4d learnest_vsq_d(learnest_v4d x) { return x * x; }
LEARNEST_SIMD_FN learnest_v8f learnest_vsq_f(learnest_v8f x) { return x * x; }
LEARNEST_SIMD_FN learnest_v4d learnest_vfabs_d(learnest_v4d x) {
  return (learnest_v4d)((learnest_v4l)x & 0x7FFFFFFFFFFFFFFFLL);
}
LEARNEST_SIMD_FN learnest_v8f learnest_vfabs_f(learnest_v8f x) {
  return (learnest_v8f)((learnest_v8i)x & 0x7FFFFFFF);
}
#endif /* LEARNEST_SIMD */

#endif /* LEARNEST_SIMD_H */
