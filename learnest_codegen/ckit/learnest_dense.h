/* learnest_dense.h -- small dense linear algebra of the kit (learnest_kit.h first).
 *
 * Square n x n matrices, stored column-major (CasADi's order) unless a function says it reads
 * a symmetric matrix, for which the order does not matter. Work arrays come from the caller
 * (no VLA, no malloc). Tested against numpy.linalg in tests/test_ckit.py.
 */
#ifndef LEARNEST_DENSE_H
#define LEARNEST_DENSE_H

#include "learnest_kit.h"

/* Before a loop over a block's rows or columns in the Gauss-Newton core and the dense kernels:
 * with GCC unrolled whole up to 16 (the blocks' sizes are fixed per build), so that the
 * indices are constants and the sums stay in registers. On a Cortex-M4F (GCC does not unroll
 * at -O2) this takes a third of the 9-state mhe_rti step's instructions off, against
 * learnest_kit.h's unroll of 4. Clang unrolls short loops of a known count whole by itself and
 * rejects a count it cannot meet on a loop of unknown count: it keeps the unroll of 4. So does
 * a model solved group by group (LEARNEST_NCOMP > 1, learnest_gn_groups.h): its blocks are the
 * groups' and the whole window's assembly is only its fallback, which unrolled whole would
 * more than double its code for a tenth fewer instructions. */
#if defined(__clang__) || (defined(LEARNEST_NCOMP) && LEARNEST_NCOMP > 1)
#define LEARNEST_UNROLL_BLOCK LEARNEST_UNROLL
#define LEARNEST_BLOCK_WHOLE 0
#elif defined(__GNUC__) && __GNUC__ >= 8
#define LEARNEST_UNROLL_BLOCK _Pragma("GCC unroll 16")
#define LEARNEST_BLOCK_WHOLE 1 /* the block loops unrolled whole: their indices are constants */
#else
#define LEARNEST_UNROLL_BLOCK
#define LEARNEST_BLOCK_WHOLE 0
#endif

/* A pointer argument whose array no other argument of the call overlaps (C99's restrict, spelt
 * so that a C++ compiler takes it too): the compiler may keep what it read through another in
 * registers across a store through it. */
#if defined(__GNUC__) || defined(__clang__)
#define LEARNEST_RESTRICT __restrict__
#else
#define LEARNEST_RESTRICT
#endif

/* The structural nonzeros of a Jacobian (nz: column-major, one byte an entry; NULL: dense).
 * Its structural zeros are exact zeros: a term one of them multiplies (by a finite factor) is
 * +-0, and adding it changes no bit of a sum that is not -0 (a sum from +0 never is; one from a
 * covariance entry only where that entry is -0, and then only the zero's sign). So the kit
 * skips those terms: with the loops unrolled and nz a constant table, the compiler drops them
 * from the code. */
LEARNEST_KIT_INLINE int learnest_nz(const unsigned char* nz, int i) { return !nz || nz[i]; }
#define LEARNEST_NZ(nz, i) learnest_nz(nz, i)

/* In-place lower Cholesky factor of the n x n matrix M (only its lower triangle is read):
 * M = L L^T. 0 (M partly overwritten) if a pivot is not positive. */
LEARNEST_KIT int learnest_cholesky(learnest_real* M, int n) {
  int i, j, k;
  LEARNEST_UNROLL_BLOCK for (j = 0; j < n; ++j) {
    learnest_real d = M[j + j * n];
    LEARNEST_UNROLL_BLOCK for (k = 0; k < j; ++k) d -= M[j + k * n] * M[j + k * n];
    if (!(d > 0)) return 0;
    d = LEARNEST_SQRT(d);
    M[j + j * n] = d;
    LEARNEST_UNROLL_BLOCK for (i = j + 1; i < n; ++i) {
      learnest_real v = M[i + j * n];
      LEARNEST_UNROLL_BLOCK for (k = 0; k < j; ++k) v -= M[i + k * n] * M[j + k * n];
      M[i + j * n] = v / d;
    }
  }
  return 1;
}

/* b <- L^-1 b for the lower triangular n x n L (column-major). */
LEARNEST_KIT void learnest_forward_subst(const learnest_real* L, int n, learnest_real* b) {
  int i, k;
  LEARNEST_UNROLL_BLOCK for (i = 0; i < n; ++i) {
    learnest_real v = b[i];
    LEARNEST_UNROLL_BLOCK for (k = 0; k < i; ++k) v -= L[i + k * n] * b[k];
    b[i] = v / L[i + i * n];
  }
}

/* b <- L^-T b for the lower triangular n x n L (column-major). */
LEARNEST_KIT void learnest_backward_subst(const learnest_real* L, int n, learnest_real* b) {
  int i, k;
  LEARNEST_UNROLL_BLOCK for (i = n - 1; i >= 0; --i) {
    learnest_real v = b[i];
    LEARNEST_UNROLL_BLOCK for (k = i + 1; k < n; ++k) v -= L[k + i * n] * b[k];
    b[i] = v / L[i + i * n];
  }
}

/* r' W r for the n x n W (column-major). */
LEARNEST_KIT learnest_real learnest_quad(const learnest_real* W, const learnest_real* r, int n) {
  learnest_real acc = 0;
  int i, j;
  LEARNEST_UNROLL_BLOCK for (j = 0; j < n; ++j) {
    learnest_real t = 0;
    LEARNEST_UNROLL_BLOCK for (i = 0; i < n; ++i) t += W[i + j * n] * r[i];
    acc += t * r[j];
  }
  return acc;
}

/* dst = src^T for n x n matrices: between row- and column-major storage. */
LEARNEST_KIT void learnest_transpose(learnest_real* dst, const learnest_real* src, int n) {
  int i, j;
  for (i = 0; i < n; ++i) {
    for (j = 0; j < n; ++j) dst[j * n + i] = src[i * n + j];
  }
}

/* 1 when the n x n A is diagonal (every off-diagonal entry exactly 0). */
LEARNEST_KIT int learnest_is_diagonal(const learnest_real* A, int n) {
  int i, j;
  for (j = 0; j < n; ++j) {
    for (i = 0; i < n; ++i) {
      if (i != j && A[i + j * n] != 0) return 0;
    }
  }
  return 1;
}

/* Ainv = A^-1 for a symmetric positive definite n x n A (either storage order: both are
 * symmetric; the result is symmetric to rounding). A diagonal A is inverted entry by entry
 * (1 / a_ii exactly, as 1 / std^2 in Python); otherwise by Cholesky, with work L (n * n).
 * 0 when A is not positive definite or the inverse is not finite. */
LEARNEST_KIT int learnest_spd_inverse(const learnest_real* A, int n, learnest_real* Ainv,
                                      learnest_real* L) {
  int i, j, k;
  if (learnest_is_diagonal(A, n)) {
    for (i = 0; i < n * n; ++i) Ainv[i] = 0;
    for (i = 0; i < n; ++i) {
      if (!(A[i * n + i] > 0)) return 0;
      Ainv[i * n + i] = 1 / A[i * n + i];
    }
    return learnest_all_finite(Ainv, n * n);
  }
  for (j = 0; j < n; ++j) {  /* L row-major here: L[i * n + j], lower */
    learnest_real d = A[j * n + j];
    LEARNEST_UNROLL_BLOCK for (k = 0; k < j; ++k) d -= L[j * n + k] * L[j * n + k];
    if (!(d > 0) || !isfinite(d)) return 0;
    L[j * n + j] = LEARNEST_SQRT(d);
    LEARNEST_UNROLL_BLOCK for (i = j + 1; i < n; ++i) {
      learnest_real v = (learnest_real)0.5 * (A[i * n + j] + A[j * n + i]);
      LEARNEST_UNROLL_BLOCK for (k = 0; k < j; ++k) v -= L[i * n + k] * L[j * n + k];
      L[i * n + j] = v / L[j * n + j];
    }
  }
  for (j = 0; j < n; ++j) {  /* column j of A^-1: solve L L^T x = e_j */
    LEARNEST_UNROLL_BLOCK for (i = 0; i < j; ++i) Ainv[i * n + j] = 0;  /* L^-1 e_j's leading zeros */
    LEARNEST_UNROLL_BLOCK for (i = j; i < n; ++i) {
      learnest_real v = i == j ? 1 : 0;
      LEARNEST_UNROLL_BLOCK for (k = j; k < i; ++k) v -= L[i * n + k] * Ainv[k * n + j];
      Ainv[i * n + j] = v / L[i * n + i];
    }
    LEARNEST_UNROLL_BLOCK for (i = n - 1; i >= 0; --i) {
      learnest_real v = Ainv[i * n + j];
      LEARNEST_UNROLL_BLOCK for (k = i + 1; k < n; ++k) v -= L[k * n + i] * Ainv[k * n + j];
      Ainv[i * n + j] = v / L[i * n + i];
    }
  }
  return learnest_all_finite(Ainv, n * n);
}

/* 1 when the n x n A is symmetric and positive semidefinite to rounding (relative 1e-10,
 * float 1e-5): the Cholesky factorisation of A + d I, d a rounding-sized shift, must succeed;
 * work L (n * n). A covariance that is not would make every later covariance meaningless. */
LEARNEST_KIT int learnest_covariance_ok(const learnest_real* A, int n, learnest_real* L) {
  const learnest_real tol = LEARNEST_IS_FLOAT ? (learnest_real)1e-5 : (learnest_real)1e-10;
  const learnest_real tiny = LEARNEST_IS_FLOAT ? (learnest_real)1e-30 : (learnest_real)1e-300;
  learnest_real scale = 0;
  int i, j, k;
  for (i = 0; i < n; ++i) scale = learnest_fmax(scale, learnest_fabs(A[i * n + i]));
  for (i = 0; i < n; ++i) {
    for (j = 0; j < i; ++j) {
      learnest_real a = A[i * n + j], b = A[j * n + i];
      if (learnest_fabs(a - b) > tol * (scale + learnest_fabs(a) + learnest_fabs(b))) return 0;
    }
  }
  for (j = 0; j < n; ++j) {
    learnest_real d = A[j * n + j] + tol * scale + tiny;
    for (k = 0; k < j; ++k) d -= L[j * n + k] * L[j * n + k];
    if (!(d > 0)) return 0;
    L[j * n + j] = LEARNEST_SQRT(d);
    for (i = j + 1; i < n; ++i) {
      learnest_real v = A[i * n + j];
      for (k = 0; k < j; ++k) v -= L[i * n + k] * L[j * n + k];
      L[i * n + j] = v / L[j * n + j];
    }
  }
  return 1;
}

/* C (m x n) = A (m x k) B, B's entry (l, j) at B[l * bl + j * bj]; A and C column-major.
 * Inlined into its two callers, so each loop indexes with its constant strides. */
LEARNEST_KIT_INLINE void learnest_mat_mul_strided(const learnest_real* A, const learnest_real* B, int bl,
                                           int bj, int m, int k, int n, learnest_real* C) {
  int i, j, l;
  for (j = 0; j < n; ++j) {
    for (i = 0; i < m; ++i) {
      learnest_real v = 0;
      for (l = 0; l < k; ++l) v += A[i + l * m] * B[l * bl + j * bj];
      C[i + j * m] = v;
    }
  }
}

/* C (m x n) = A (m x k) B (k x n); all column-major. */
LEARNEST_KIT void learnest_mat_mul(const learnest_real* A, const learnest_real* B, int m, int k,
                                   int n, learnest_real* C) {
  learnest_mat_mul_strided(A, B, 1, k, m, k, n, C);
}

/* C (m x n) = A (m x k) B^T (B: n x k); all column-major. */
LEARNEST_KIT void learnest_mat_mul_t(const learnest_real* A, const learnest_real* B, int m, int k,
                                     int n, learnest_real* C) {
  learnest_mat_mul_strided(A, B, n, 1, m, k, n, C);
}

/* 1 when every variance (diagonal entry) of the n x n A is in the precision's range
 * (learnest_status.h LEARNEST_VARIANCE_MIN/_MAX, a float build LEARNEST_VARIANCE_FLOAT32_*),
 * or is 0 where definite is 0: a variance beyond it has an inverse or a square the estimator
 * cannot carry (runtime/limits.py). */
LEARNEST_KIT int learnest_variances_ok(const learnest_real* A, int n, int definite) {
  const learnest_real lo = LEARNEST_IS_FLOAT ? (learnest_real)LEARNEST_VARIANCE_FLOAT32_MIN
                                             : (learnest_real)LEARNEST_VARIANCE_MIN;
  const learnest_real hi = LEARNEST_IS_FLOAT ? (learnest_real)LEARNEST_VARIANCE_FLOAT32_MAX
                                             : (learnest_real)LEARNEST_VARIANCE_MAX;
  int i;
  for (i = 0; i < n; ++i) {
    const learnest_real v = A[i * n + i];
    if (!((v >= lo && v <= hi) || (!definite && v == 0))) return 0;
  }
  return 1;
}

/* A covariance as an API call gives it (n x n, row-major) checked: finite (else
 * LEARNEST_NONFINITE_INPUT), symmetric and positive semidefinite to rounding (else
 * LEARNEST_NOT_POSITIVE_DEFINITE); dst = its column-major copy; work holds n * n. */
LEARNEST_KIT int learnest_covariance_in(const learnest_real* A, int n, learnest_real* dst,
                                        learnest_real* work) {
  if (!learnest_all_finite(A, n * n)) return LEARNEST_NONFINITE_INPUT;
  if (!learnest_covariance_ok(A, n, work)) return LEARNEST_NOT_POSITIVE_DEFINITE;
  learnest_transpose(dst, A, n);
  return LEARNEST_OK;
}

/* Scale row and column i of the symmetric n x n A (either order) by sqrt(ceiling_i / A_ii)
 * where A_ii exceeds ceiling_i: the variances are then at most the ceiling and the
 * correlations stay (A stays positive semidefinite); s holds n. Returns 1 when a variance
 * was capped. */
LEARNEST_KIT int learnest_cap_variances(learnest_real* A, int n, const learnest_real* ceiling,
                                        learnest_real* s) {
  int i, j, capped = 0;
  for (i = 0; i < n; ++i) {
    s[i] = A[i * n + i] > ceiling[i] ? LEARNEST_SQRT(ceiling[i] / A[i * n + i]) : 1;
    capped |= s[i] != 1;
  }
  if (!capped) return 0;
  for (i = 0; i < n; ++i) {
    for (j = 0; j < n; ++j) A[i * n + j] *= s[i] * s[j];
  }
  return 1;
}

/* A <- (A + A^T) / 2 for the n x n A. */
LEARNEST_KIT void learnest_symmetrise(learnest_real* A, int n) {
  int i, j;
  for (i = 0; i < n; ++i) {
    for (j = 0; j < i; ++j) {
      learnest_real v = (learnest_real)0.5 * (A[i * n + j] + A[j * n + i]);
      A[i * n + j] = A[j * n + i] = v;
    }
  }
}

#endif /* LEARNEST_DENSE_H */
