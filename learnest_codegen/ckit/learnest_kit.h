/* learnest_kit.h -- the prelude of the C kit every estimator of learnest_codegen is built on.
 *
 * The kit is C99 (and C++-clean) source in headers: each estimator's generated translation
 * unit defines its real type and sizes, names its generated model, and includes the kit, so
 * that every kit function is static to that translation unit. Two estimators of any sizes
 * and precisions therefore link into one image without a symbol clash (only the
 * <prefix>_* API is exported), and each copy is compiled for its own fixed sizes.
 *
 * Define before including:
 *   LEARNEST_REAL   the real type, double or float.
 * This header gives the kit's function specifier, its real type, and small helpers every
 * module uses; learnest_math.h chooses the math routines by precision. docs/c_kit.md describes the
 * kit and how an estimator is added.
 */
#ifndef LEARNEST_KIT_H
#define LEARNEST_KIT_H

#ifndef LEARNEST_REAL
#error "learnest_kit.h: define LEARNEST_REAL (double or float) before including the kit"
#endif

#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "learnest_math.h"
#include "learnest_status.h"

/* Every kit function is static (private to the estimator's translation unit); an estimator
 * that does not use one must not get a warning for it. */
#if defined(__GNUC__) || defined(__clang__)
#define LEARNEST_KIT static __attribute__((unused))
#else
#define LEARNEST_KIT static
#endif

/* A kit function that is a few lines of its one caller, kept in the caller's frame (as if
 * written there): the stack a step needs stays what one frame says. */
#if defined(__GNUC__) || defined(__clang__)
#define LEARNEST_KIT_INLINE static inline __attribute__((always_inline, unused))
#else
#define LEARNEST_KIT_INLINE static inline
#endif

typedef LEARNEST_REAL learnest_real;

/* Before a loop over a block's rows or columns: unrolled by the compiler (the blocks are
 * small and of fixed size; GCC's -O2 would not unroll them: -12 % instructions for mhe_rti). */
#if defined(__clang__)
#define LEARNEST_UNROLL _Pragma("unroll 4")
#elif defined(__GNUC__) && __GNUC__ >= 8
#define LEARNEST_UNROLL _Pragma("GCC unroll 4")
#else
#define LEARNEST_UNROLL
#endif

/* Math routines by precision: learnest_math.h (LEARNEST_SQRT, LEARNEST_FABS). */
#define LEARNEST_IS_FLOAT (sizeof(learnest_real) == sizeof(float))

/* Alignment of the estimator inside the caller's workspace (any buffer: init aligns). */
#define LEARNEST_ALIGN 16u

#define LEARNEST_CAT_(a, b) a##b
#define LEARNEST_CAT(a, b) LEARNEST_CAT_(a, b)
#define LEARNEST_MAX(a, b) ((a) > (b) ? (a) : (b))
/* A compile-time check: a negative array size stops the build with the name in the message. */
#define LEARNEST_STATIC_ASSERT(cond, name) typedef char learnest_assert_##name[(cond) ? 1 : -1]

/* 1 when the n values are all finite. */
LEARNEST_KIT int learnest_all_finite(const learnest_real* v, int n) {
  int i;
  for (i = 0; i < n; ++i) {
    if (!isfinite(v[i])) return 0;
  }
  return 1;
}

/* LEARNEST_OK when every flag of valid (n) is 0 or 1 (NULL: every output is valid), else
 * LEARNEST_BAD_ARGUMENT: any other byte is a caller's mistake (a wrong pointer), not a flag. */
LEARNEST_KIT int learnest_check_flags(const unsigned char* valid, int n) {
  int i;
  for (i = 0; valid && i < n; ++i) {
    if (valid[i] > 1) return LEARNEST_BAD_ARGUMENT;
  }
  return LEARNEST_OK;
}

/* The address at or after mem aligned to LEARNEST_ALIGN. */
LEARNEST_KIT void* learnest_align(void* mem) {
  uintptr_t a = (uintptr_t)mem;
  return (void*)((a + (LEARNEST_ALIGN - 1u)) & ~(uintptr_t)(LEARNEST_ALIGN - 1u));
}

#endif /* LEARNEST_KIT_H */
