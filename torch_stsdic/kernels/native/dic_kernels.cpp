// Fused CPU kernels of torch_stsdic: B-spline sampling and the joint IC-GN right-hand side.
//
// Built on first use by torch_stsdic/native/ with the system C++ compiler (the same one
// torch.compile needs) and loaded with ctypes; plain C ABI, no torch headers, so the build
// takes about a second. Every kernel works on a range [i0, i1) of its rows so that Python
// threads (ctypes releases the GIL) split the work without an OpenMP runtime of our own.
//
// Each kernel's parameter list is written once, in its STS_KERNEL definition below; the
// library hands that declaration (names as written, types as the compiler sees them) and the
// kernel's address to native/ through the sts_kernel_* functions at the end of this file.
// native/ has no copy of any signature: it builds the ctypes prototypes from these
// declarations and calls every kernel by parameter name, checked.
//
// Conventions are those of torch_stsdic/interpolation.py (sample_kernel) and
// torch_stsdic/formulations/joint_ic.py (ic_rhs_kernel); the tests compare both paths.

#include <algorithm>
#include <cmath>
#include <cstring>
#include <cstdint>
#include <limits>
#include <string>
#include <type_traits>
#include <vector>

#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#endif

namespace {

// ---- kernel declarations -------------------------------------------------------------------
// STS_KERNEL(name, (parameters)) { body } defines `template <typename T> int name(parameters)`
// and registers its float and double instances ("name_f32", "name_f64") with
//   - the parameter list as written (stringified by the preprocessor from the same tokens the
//     compiler compiles): parameter names, and `nullable<...>` on pointers that may be null;
//   - the parameter kinds as the compiler sees the instance's type: "i32", "i64", "f32",
//     "f64", or "*" + the element kind for a pointer ("*f64", "*u8"); a parameter type
//     without a kind is a compile error;
//   - the instance's address.
// native/declarations.py reads them through sts_kernel_count/name/params/kinds/address
// (extern "C", at the end of this file), checks that the written list parses to the compiled
// kinds, and builds each ctypes prototype from the kinds. Kernels return 0, or non-zero for
// arguments they reject (e.g. an unsupported spline order).

template <typename P>
using nullable = P*;  // a pointer parameter that may be null (say what null means)

template <typename A>
inline constexpr bool no_kind = false;

template <typename A>
std::string kind_of() {
  using B = std::remove_cv_t<A>;
  if constexpr (std::is_pointer_v<B>) {
    return "*" + kind_of<std::remove_pointer_t<B>>();
  } else if constexpr (std::is_same_v<B, int32_t>) {
    return "i32";
  } else if constexpr (std::is_same_v<B, int64_t>) {
    return "i64";
  } else if constexpr (std::is_same_v<B, uint8_t>) {
    return "u8";
  } else if constexpr (std::is_same_v<B, float>) {
    return "f32";
  } else if constexpr (std::is_same_v<B, double>) {
    return "f64";
  } else {
    static_assert(no_kind<B>, "kernel parameter type without a ctypes kind");
    return "";
  }
}

template <typename... A>
std::string kinds_of(int (*)(A...)) {  // only kernels returning int register
  std::string s;
  ((s += (s.empty() ? "" : ","), s += kind_of<A>()), ...);
  return s;
}

struct Declaration {
  const char* name;
  const char* params;
  std::string kinds[2];  // float, double instance
  void* address[2];
};

std::vector<Declaration>& declarations() {
  static std::vector<Declaration> all;
  return all;
}

struct Declare {
  template <typename F32, typename F64>
  Declare(const char* name, const char* params, F32* f32, F64* f64) {
    declarations().push_back({name, params, {kinds_of(f32), kinds_of(f64)},
                              {reinterpret_cast<void*>(f32), reinterpret_cast<void*>(f64)}});
  }
};

#define STS_KERNEL(name, params)                                                        \
  template <typename T>                                                                 \
  int name params;                                                                      \
  const Declare name##_declared(#name, #params, &name<float>, &name<double>);           \
  template <typename T>                                                                 \
  int name params

struct Geo {
  int64_t wp;      // padded width of one coefficient plane
  double x_lo, x_hi, y_lo, y_hi;  // clamp range of the tap origin
  int64_t shift;   // index shift of the first tap
};

template <typename T>
inline void cubic_weights(T f, T* w) {
  constexpr T sixth = T(1) / T(6);
  const T f2 = f * f, f3 = f2 * f, g = T(1) - f;
  w[0] = g * g * g * sixth;
  w[1] = (T(0.5) * f3 - f2) + T(2) / T(3);
  w[2] = ((T(-0.5) * f3 + T(0.5) * f2) + T(0.5) * f) + sixth;
  w[3] = f3 * sixth;
}

template <typename T>
inline void cubic_dweights(T f, T* d) {
  const T f2 = f * f, g = T(1) - f;
  d[0] = T(-0.5) * g * g;
  d[1] = T(1.5) * f2 - T(2) * f;
  d[2] = T(-1.5) * f2 + f + T(0.5);
  d[3] = T(0.5) * f2;
}

// centred quintic B-spline and its derivative at d
template <typename T>
inline void quintic(T d, T* b, T* db) {
  const T a = std::fabs(d);
  const T s = d > T(0) ? T(1) : (d < T(0) ? T(-1) : T(0));
  const T a2 = a * a, a3 = a2 * a, a4 = a3 * a, a5 = a4 * a;
  if (a < T(1)) {
    *b = (T(66) - T(60) * a2 + T(30) * a4 - T(10) * a5) / T(120);
    *db = s * (T(-120) * a + T(120) * a3 - T(50) * a4) / T(120);
  } else if (a < T(2)) {
    *b = (T(51) + T(75) * a - T(210) * a2 + T(150) * a3 - T(45) * a4 + T(5) * a5) / T(120);
    *db = s * (T(75) - T(420) * a + T(450) * a2 - T(180) * a3 + T(25) * a4) / T(120);
  } else {
    const T r = std::max(T(3) - a, T(0));
    const T r2 = r * r, r4 = r2 * r2;
    *b = r4 * r / T(120);
    *db = s * T(-5) * r4 / T(120);
  }
}

template <typename T, int ORDER>
inline void weights(T f, T* w, T* dw, bool grad) {
  if constexpr (ORDER == 3) {
    cubic_weights(f, w);
    if (grad) cubic_dweights(f, dw);
  } else {
    T dummy;
    for (int i = 0; i < 6; ++i) quintic(f - T(i - 2), &w[i], grad ? &dw[i] : &dummy);
  }
}

// Tap origin (32-bit index in the plane) and fractions of one point (x, y) after clamping it
// to the coefficient grid (a NaN coordinate to its low end, as the AVX2 path's max/min do: a
// point of NaN parameters reads inside the plane, never outside it).
template <typename T>
inline void tap_origin(const Geo& g, T x, T y, int32_t* idx, T* fx, T* fy) {
  const T xlo = T(g.x_lo), xhi = T(g.x_hi), ylo = T(g.y_lo), yhi = T(g.y_hi);
  x = x >= xlo ? (x > xhi ? xhi : x) : xlo;
  y = y >= ylo ? (y > yhi ? yhi : y) : ylo;
  const T x0 = std::floor(x), y0 = std::floor(y);
  *fx = x - x0;
  *fy = y - y0;
  *idx = (int32_t(y0) + int32_t(g.shift)) * int32_t(g.wp) + int32_t(x0) + int32_t(g.shift);
}

#if defined(__AVX2__) && defined(__FMA__)
// tap_origin of eight float points at once: the indices stored to idx, the fractions
// returned.
struct TapOrigins8 {
  __m256 xlo, xhi, ylo, yhi;
  __m256i wp, sh;
  explicit TapOrigins8(const Geo& g)
      : xlo(_mm256_set1_ps(float(g.x_lo))), xhi(_mm256_set1_ps(float(g.x_hi))),
        ylo(_mm256_set1_ps(float(g.y_lo))), yhi(_mm256_set1_ps(float(g.y_hi))),
        wp(_mm256_set1_epi32(int32_t(g.wp))), sh(_mm256_set1_epi32(int32_t(g.shift))) {}
  void operator()(__m256 x, __m256 y, int32_t* idx, __m256* fx, __m256* fy) const {
    x = _mm256_min_ps(_mm256_max_ps(x, xlo), xhi);
    y = _mm256_min_ps(_mm256_max_ps(y, ylo), yhi);
    const __m256 x0 = _mm256_floor_ps(x), y0 = _mm256_floor_ps(y);
    *fx = _mm256_sub_ps(x, x0);
    *fy = _mm256_sub_ps(y, y0);
    const __m256i iy = _mm256_add_epi32(_mm256_cvttps_epi32(y0), sh);
    const __m256i ix = _mm256_add_epi32(_mm256_cvttps_epi32(x0), sh);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(idx),
                        _mm256_add_epi32(_mm256_mullo_epi32(iy, wp), ix));
  }
};
#endif

// Tap origins and fractions of the points (ox + dxu[s], oy + dyv[s]), s < ns.
template <typename T>
inline void tap_origins(const Geo& g, T ox, T oy, const T* dxu, const T* dyv, int64_t ns,
                        int32_t* idx, T* fxs, T* fys) {
  int64_t s = 0;
#if defined(__AVX2__) && defined(__FMA__)
  if constexpr (sizeof(T) == 4) {
    const TapOrigins8 taps(g);
    const __m256 vox = _mm256_set1_ps(ox), voy = _mm256_set1_ps(oy);
    for (; s + 8 <= ns; s += 8) {
      __m256 fx, fy;
      taps(_mm256_add_ps(vox, _mm256_loadu_ps(dxu + s)),
           _mm256_add_ps(voy, _mm256_loadu_ps(dyv + s)), idx + s, &fx, &fy);
      _mm256_storeu_ps(fxs + s, fx);
      _mm256_storeu_ps(fys + s, fy);
    }
  }
#endif
  for (; s < ns; ++s) tap_origin<T>(g, ox + dxu[s], oy + dyv[s], idx + s, fxs + s, fys + s);
}

#if defined(__AVX2__) && defined(__FMA__)
// AVX2 helpers of the float cubic path: the 4 tap weights of x (low 128 bits) and of y (high
// 128 bits) as one cubic polynomial per lane (Horner); value = sum of rows r_j * (wx * wy_j)
// with two rows of 4 taps per 256-bit register.
struct CubicAvx {
  __m256 c3 = _mm256_setr_ps(-1.f / 6, 0.5f, -0.5f, 1.f / 6, -1.f / 6, 0.5f, -0.5f, 1.f / 6);
  __m256 c2 = _mm256_setr_ps(0.5f, -1.f, 0.5f, 0.f, 0.5f, -1.f, 0.5f, 0.f);
  __m256 c1 = _mm256_setr_ps(-0.5f, 0.f, 0.5f, 0.f, -0.5f, 0.f, 0.5f, 0.f);
  __m256 c0 = _mm256_setr_ps(1.f / 6, 2.f / 3, 1.f / 6, 0.f, 1.f / 6, 2.f / 3, 1.f / 6, 0.f);
  // derivative weights (quadratic)
  __m256 d2 = _mm256_setr_ps(-0.5f, 1.5f, -1.5f, 0.5f, -0.5f, 1.5f, -1.5f, 0.5f);
  __m256 d1 = _mm256_setr_ps(1.f, -2.f, 1.f, 0.f, 1.f, -2.f, 1.f, 0.f);
  __m256 d0 = _mm256_setr_ps(-0.5f, 0.f, 0.5f, 0.f, -0.5f, 0.f, 0.5f, 0.f);

  static __m256 frac(float fx, float fy) {
    return _mm256_set_m128(_mm_set1_ps(fy), _mm_set1_ps(fx));
  }
  __m256 weights(__m256 f) const {
    return _mm256_fmadd_ps(_mm256_fmadd_ps(_mm256_fmadd_ps(c3, f, c2), f, c1), f, c0);
  }
  __m256 dweights(__m256 f) const { return _mm256_fmadd_ps(_mm256_fmadd_ps(d2, f, d1), f, d0); }
  // (w_y[0] | w_y[1]) and (w_y[2] | w_y[3]) broadcast over the 4 x taps of a row
  static void rows_of(__m128 wy, __m256* w01, __m256* w23) {
    *w01 = _mm256_set_m128(_mm_permute_ps(wy, 0x55), _mm_permute_ps(wy, 0x00));
    *w23 = _mm256_set_m128(_mm_permute_ps(wy, 0xFF), _mm_permute_ps(wy, 0xAA));
  }
  static float hsum(__m256 acc) {
    __m128 q = _mm_add_ps(_mm256_castps256_ps128(acc), _mm256_extractf128_ps(acc, 1));
    q = _mm_add_ps(q, _mm_movehl_ps(q, q));
    q = _mm_add_ss(q, _mm_shuffle_ps(q, q, 0x55));
    return _mm_cvtss_f32(q);
  }
};
#endif

// Values of one frame at the points (ox + dxu[s], oy + dyv[s]), s < ns, into out[s]; with
// GRAD also d/dx and d/dy into gx[s], gy[s] (else gx, gy are not touched).
// Pass 1 (vectorised by the compiler): clamp, floor, 32-bit tap index within the plane and
// the fractions; pass 2: the taps.
template <typename T, int ORDER, bool GRAD = false>
inline void sample_points(const T* plane, const Geo& g, T ox, T oy, const T* dxu,
                          const T* dyv, int64_t ns, int32_t* idx, T* fxs, T* fys, T* out,
                          T* gx = nullptr, T* gy = nullptr) {
  tap_origins<T>(g, ox, oy, dxu, dyv, ns, idx, fxs, fys);
  const int64_t wpl = g.wp;
#if defined(__AVX2__) && defined(__FMA__)
  if constexpr (ORDER == 3 && sizeof(T) == 4) {
    const CubicAvx k;
    int64_t s = 0;
    if constexpr (!GRAD) {
      // eight points at a time: their 8 partial sums each reduced together (a transposing
      // tree of horizontal adds, one store), not one horizontal sum and store per point
      for (; s + 8 <= ns; s += 8) {
        __m256 acc[8];
        for (int q = 0; q < 8; ++q) {
          const __m256 wv = k.weights(CubicAvx::frac(fxs[s + q], fys[s + q]));
          const __m128 wx = _mm256_castps256_ps128(wv);
          const __m256 wxx = _mm256_set_m128(wx, wx);
          __m256 wy01, wy23;
          CubicAvx::rows_of(_mm256_extractf128_ps(wv, 1), &wy01, &wy23);
          const float* r = plane + idx[s + q];
          const __m256 r01 = _mm256_loadu2_m128(r + wpl, r);
          const __m256 r23 = _mm256_loadu2_m128(r + 3 * wpl, r + 2 * wpl);
          acc[q] = _mm256_fmadd_ps(r23, _mm256_mul_ps(wxx, wy23),
                                   _mm256_mul_ps(r01, _mm256_mul_ps(wxx, wy01)));
        }
        const __m256 u0 = _mm256_hadd_ps(_mm256_hadd_ps(acc[0], acc[1]),
                                         _mm256_hadd_ps(acc[2], acc[3]));
        const __m256 u1 = _mm256_hadd_ps(_mm256_hadd_ps(acc[4], acc[5]),
                                         _mm256_hadd_ps(acc[6], acc[7]));
        _mm256_storeu_ps(out + s, _mm256_add_ps(_mm256_permute2f128_ps(u0, u1, 0x20),
                                                _mm256_permute2f128_ps(u0, u1, 0x31)));
      }
    }
    for (; s < ns; ++s) {
      const __m256 f = CubicAvx::frac(fxs[s], fys[s]);
      const __m256 wv = k.weights(f);
      const __m128 wx = _mm256_castps256_ps128(wv);
      const __m256 wxx = _mm256_set_m128(wx, wx);
      __m256 wy01, wy23;
      CubicAvx::rows_of(_mm256_extractf128_ps(wv, 1), &wy01, &wy23);
      const float* r = plane + idx[s];
      const __m256 r01 = _mm256_loadu2_m128(r + wpl, r);
      const __m256 r23 = _mm256_loadu2_m128(r + 3 * wpl, r + 2 * wpl);
      if constexpr (GRAD) {
        const __m256 dv = k.dweights(f);
        const __m128 dx = _mm256_castps256_ps128(dv);
        const __m256 dxx = _mm256_set_m128(dx, dx);
        __m256 dy01, dy23;
        CubicAvx::rows_of(_mm256_extractf128_ps(dv, 1), &dy01, &dy23);
        const __m256 a01 = _mm256_mul_ps(r01, wxx), a23 = _mm256_mul_ps(r23, wxx);
        out[s] = CubicAvx::hsum(_mm256_fmadd_ps(a23, wy23, _mm256_mul_ps(a01, wy01)));
        gy[s] = CubicAvx::hsum(_mm256_fmadd_ps(a23, dy23, _mm256_mul_ps(a01, dy01)));
        const __m256 b01 = _mm256_mul_ps(r01, dxx), b23 = _mm256_mul_ps(r23, dxx);
        gx[s] = CubicAvx::hsum(_mm256_fmadd_ps(b23, wy23, _mm256_mul_ps(b01, wy01)));
      } else {
        out[s] = CubicAvx::hsum(_mm256_fmadd_ps(r23, _mm256_mul_ps(wxx, wy23),
                                                _mm256_mul_ps(r01, _mm256_mul_ps(wxx, wy01))));
      }
    }
    return;
  }
#endif
  constexpr int N = ORDER + 1;
  for (int64_t s = 0; s < ns; ++s) {
    T wx[N], wy[N], dwx[N], dwy[N];
    weights<T, ORDER>(fxs[s], wx, dwx, GRAD);
    weights<T, ORDER>(fys[s], wy, dwy, GRAD);
    const T* r = plane + idx[s];
    T val = 0, vx = 0, vy = 0;
    for (int j = 0; j < N; ++j) {
      T acc = 0, accd = 0;
      for (int i = 0; i < N; ++i) {
        acc += r[j * wpl + i] * wx[i];
        if constexpr (GRAD) accd += r[j * wpl + i] * dwx[i];
      }
      val += acc * wy[j];
      if constexpr (GRAD) {
        vx += accd * wy[j];
        vy += acc * dwy[j];
      }
    }
    out[s] = val;
    if constexpr (GRAD) {
      gx[s] = vx;
      gy[s] = vy;
    }
  }
}

#if defined(__AVX2__) && defined(__FMA__)
// Values of one float frame at the points (ox + dxu[s], oy + dyv[s]), s < ns (cubic
// B-spline; the IC-GN residual's path): pass 1, eight points at a time, the tap origins, the
// x fractions and the four y weights of every point (wy: (4, ns), one row per tap row);
// pass 2, per point, its four tap rows (128-bit loads) weighted by its y weights (broadcast
// loads), then by its x weights, eight points reduced together. No lane shuffles but the
// final reduction: the loads and the FMAs set the pace.
inline void cubic_values_f32(const float* plane, const Geo& g, float ox, float oy,
                             const float* dxu, const float* dyv, int64_t ns, int32_t* idx,
                             float* fxs, float* wy, float* out) {
  const int64_t wpl = g.wp;
  float* wy0 = wy;
  float* wy1 = wy + ns;
  float* wy2 = wy + 2 * ns;
  float* wy3 = wy + 3 * ns;
  int64_t s = 0;
  {
    const TapOrigins8 taps(g);
    const __m256 vox = _mm256_set1_ps(ox), voy = _mm256_set1_ps(oy);
    const __m256 sixth = _mm256_set1_ps(1.f / 6), half = _mm256_set1_ps(0.5f);
    const __m256 one = _mm256_set1_ps(1.f), twoth = _mm256_set1_ps(2.f / 3);
    for (; s + 8 <= ns; s += 8) {
      __m256 fx, f;
      taps(_mm256_add_ps(vox, _mm256_loadu_ps(dxu + s)),
           _mm256_add_ps(voy, _mm256_loadu_ps(dyv + s)), idx + s, &fx, &f);
      _mm256_storeu_ps(fxs + s, fx);
      // the cubic B-spline's y weights (1-f)^3/6, 2/3 - f^2 + f^3/2, ..., f^3/6
      const __m256 f2 = _mm256_mul_ps(f, f), f3 = _mm256_mul_ps(f2, f);
      const __m256 g1 = _mm256_sub_ps(one, f);
      _mm256_storeu_ps(wy0 + s, _mm256_mul_ps(sixth, _mm256_mul_ps(_mm256_mul_ps(g1, g1), g1)));
      _mm256_storeu_ps(wy1 + s, _mm256_fmadd_ps(half, f3, _mm256_sub_ps(twoth, f2)));
      _mm256_storeu_ps(wy2 + s, _mm256_add_ps(_mm256_fmadd_ps(half, _mm256_sub_ps(f2, f3),
                                                              _mm256_mul_ps(half, f)), sixth));
      _mm256_storeu_ps(wy3 + s, _mm256_mul_ps(sixth, f3));
    }
  }
  for (int64_t r = s; r < ns; ++r) {
    float fy, w[4], dw[4];
    tap_origin<float>(g, ox + dxu[r], oy + dyv[r], idx + r, fxs + r, &fy);
    weights<float, 3>(fy, w, dw, false);
    wy0[r] = w[0];
    wy1[r] = w[1];
    wy2[r] = w[2];
    wy3[r] = w[3];
  }
  const __m128 c3 = _mm_setr_ps(-1.f / 6, 0.5f, -0.5f, 1.f / 6);
  const __m128 c2 = _mm_setr_ps(0.5f, -1.f, 0.5f, 0.f);
  const __m128 c1 = _mm_setr_ps(-0.5f, 0.f, 0.5f, 0.f);
  const __m128 c0 = _mm_setr_ps(1.f / 6, 2.f / 3, 1.f / 6, 0.f);
  auto point = [&](int64_t t) {
    const __m128 f = _mm_broadcast_ss(fxs + t);
    const __m128 wx = _mm_fmadd_ps(_mm_fmadd_ps(_mm_fmadd_ps(c3, f, c2), f, c1), f, c0);
    const float* r = plane + idx[t];
    __m128 a = _mm_mul_ps(_mm_loadu_ps(r), _mm_broadcast_ss(wy0 + t));
    a = _mm_fmadd_ps(_mm_loadu_ps(r + wpl), _mm_broadcast_ss(wy1 + t), a);
    a = _mm_fmadd_ps(_mm_loadu_ps(r + 2 * wpl), _mm_broadcast_ss(wy2 + t), a);
    a = _mm_fmadd_ps(_mm_loadu_ps(r + 3 * wpl), _mm_broadcast_ss(wy3 + t), a);
    return _mm_mul_ps(a, wx);
  };
  s = 0;
  for (; s + 8 <= ns; s += 8) {
    __m128 acc[8];
    for (int q = 0; q < 8; ++q) acc[q] = point(s + q);
    const __m128 lo = _mm_hadd_ps(_mm_hadd_ps(acc[0], acc[1]), _mm_hadd_ps(acc[2], acc[3]));
    const __m128 hi = _mm_hadd_ps(_mm_hadd_ps(acc[4], acc[5]), _mm_hadd_ps(acc[6], acc[7]));
    _mm_storeu_ps(out + s, lo);
    _mm_storeu_ps(out + s + 4, hi);
  }
  for (; s < ns; ++s) {
    __m128 q = point(s);
    q = _mm_add_ps(q, _mm_movehl_ps(q, q));
    q = _mm_add_ss(q, _mm_shuffle_ps(q, q, 0x55));
    out[s] = _mm_cvtss_f32(q);
  }
}
#endif

// Generic sampling of points x[i], y[i], i in [i0, i1), in the plane at off[i / period]
// (period 0: off[0] for all; off null: plane 0), in blocks of constant plane.
template <typename T, int ORDER>
void sample_range(const T* flat, const Geo& g, const T* x, const T* y, const int64_t* off,
                  int64_t off_period, int64_t i0, int64_t i1, T* val, T* gx, T* gy) {
  const int64_t chunk = 1024;
  std::vector<int32_t> idx(chunk);
  std::vector<T> fxs(chunk), fys(chunk);
  const bool grad = gx != nullptr && gy != nullptr;
  int64_t i = i0;
  while (i < i1) {
    int64_t end = std::min(i1, i + chunk);
    int64_t o = 0;
    if (off) {
      const int64_t j = off_period > 0 ? i / off_period : 0;
      o = off[j];
      if (off_period > 0) end = std::min(end, (j + 1) * off_period);
    }
    if (grad) {
      sample_points<T, ORDER, true>(flat + o, g, T(0), T(0), x + i, y + i, end - i,
                                    idx.data(), fxs.data(), fys.data(), val + i, gx + i, gy + i);
    } else {
      sample_points<T, ORDER>(flat + o, g, T(0), T(0), x + i, y + i, end - i, idx.data(),
                              fxs.data(), fys.data(), val + i);
    }
    i = end;
  }
}

// ---- the kernels (see STS_KERNEL) --------------------------------------------------------

// Points: values (and, with gx and gy, d/dx and d/dy) at (x[i], y[i]), i in [i0, i1), in the
// plane at off[i / off_period] (off_period 0: off[0] for all points; off null: plane 0).
// flat: the coefficient planes; wp, clamp range, shift, order: see interpolation.kernel_args.
STS_KERNEL(sts_sample, (const T* flat, int64_t wp, double x_lo, double x_hi, double y_lo,
                        double y_hi, int64_t shift, int order, const T* x, const T* y,
                        nullable<const int64_t> off, int64_t off_period, int64_t i0,
                        int64_t i1, T* val, nullable<T> gx, nullable<T> gy)) {
  const Geo g{wp, x_lo, x_hi, y_lo, y_hi, shift};
  if (order == 3) {
    sample_range<T, 3>(flat, g, x, y, off, off_period, i0, i1, val, gx, gy);
  } else if (order == 5) {
    sample_range<T, 5>(flat, g, x, y, off, off_period, i0, i1, val, gx, gy);
  } else {
    return 1;
  }
  return 0;
}

// Subsets: rows i in [i0, i1), samples (px[i] + dx[s], py[i] + dy[s]) in the plane at
// off[i] (off null: plane 0); val, gx, gy are (N, ns) (gx, gy null: values only).
STS_KERNEL(sts_subsets, (const T* flat, int64_t wp, double x_lo, double x_hi, double y_lo,
                         double y_hi, int64_t shift, int order, int64_t i0, int64_t i1,
                         int64_t ns, const T* px, const T* py, const T* dx, const T* dy,
                         nullable<const int64_t> off, T* val, nullable<T> gx,
                         nullable<T> gy)) {
  const Geo g{wp, x_lo, x_hi, y_lo, y_hi, shift};
  std::vector<int32_t> idx(ns);
  std::vector<T> fxs(ns), fys(ns);
  const bool grad = gx != nullptr && gy != nullptr;
  if (order != 3 && order != 5) return 1;
  for (int64_t i = i0; i < i1; ++i) {
    const T* plane = flat + (off ? off[i] : 0);
    T* v = val + i * ns;
    if (order == 3 && grad)
      sample_points<T, 3, true>(plane, g, px[i], py[i], dx, dy, ns, idx.data(), fxs.data(),
                                fys.data(), v, gx + i * ns, gy + i * ns);
    else if (order == 3)
      sample_points<T, 3>(plane, g, px[i], py[i], dx, dy, ns, idx.data(), fxs.data(),
                          fys.data(), v);
    else if (grad)
      sample_points<T, 5, true>(plane, g, px[i], py[i], dx, dy, ns, idx.data(), fxs.data(),
                                fys.data(), v, gx + i * ns, gy + i * ns);
    else
      sample_points<T, 5>(plane, g, px[i], py[i], dx, dy, ns, idx.data(), fxs.data(),
                          fys.data(), v);
  }
  return 0;
}

// Windows: rows i in [i0, i1) of out (N, wy * wx) = the wy x wx window of the image src
// whose top-left pixel is at the flat index base[i] (image rows ws values apart): whole-pixel
// subsets gathered from a per-pixel image (interpolation.BSplineImage._subsets_on_grid),
// one copy per window row.
STS_KERNEL(sts_windows, (int64_t i0, int64_t i1, const T* src, int64_t ws,
                         const int64_t* base, int64_t wy, int64_t wx, T* out)) {
  if (wy < 1 || wx < 1) return 1;
  for (int64_t i = i0; i < i1; ++i) {
    const T* from = src + base[i];
    T* to = out + i * wy * wx;
    for (int64_t r = 0; r < wy; ++r) std::memcpy(to + r * wx, from + r * ws, wx * sizeof(T));
  }
  return 0;
}

template <typename T>
inline T dot(const T* a, const T* b, int64_t n) {
  T acc = 0;
#pragma omp simd reduction(+ : acc)
  for (int64_t s = 0; s < n; ++s) acc += a[s] * b[s];
  return acc;
}

// One joint IC-GN right-hand side per POI (see formulations/joint_ic.py, ic_rhs_kernel):
//   b = sum_t J_t^T e_t,  J_t = [gx B, gx dt_t, gy B, gy dt_t],
//   e_t = w (ft - a_t (g_t - mean g_t))   (ZNSSD, a_t = |ft| / |g_t - mean g_t|)
//   e_t = w (ft - g_t)                    (SSD)
// Per frame: sample the subset, its weighted mean and norm, the residual, then
// 2 (Ks + 1) dot products; frame sums in double.
//
// IcProblem holds what every row of a call shares, IcScratch one thread's buffers, and
// ic_rhs_row computes one row; sts_ic_rhs runs it over a range of rows (one step of a batch),
// sts_ic_solve iterates each row to convergence (no barrier between iterations).
template <typename T>
struct IcProblem {
  const T* flat;
  Geo g;
  int64_t nt, ns, ks, k;
  bool has_time, znssd;
  const T *px, *py, *dx, *dy, *dt;
  const int64_t* frame_off;
  const T *ft, *fnorm, *fgx, *fgy, *w;
  const int64_t* ref_rows;
  const T* motion;
  const int64_t* count;  // (N,) each data row's frames in use: its first count[i] (null: nt)
  double w_img, h;
  std::vector<T> bt;  // basis transposed (Ks, S)
  T inv_wsum;

  IcProblem(const T* flat_, const Geo& g_, int64_t nt_, int64_t ns_, int64_t ks_, int64_t k_,
            bool has_time_, bool znssd_, const T* px_, const T* py_, const T* dx_,
            const T* dy_, const T* basis, const T* dt_, const int64_t* frame_off_,
            const T* ft_, const T* fnorm_, const T* fgx_, const T* fgy_, const T* w_,
            const int64_t* ref_rows_, const T* motion_, const int64_t* count_,
            double w_img_, double h_)
      : flat(flat_), g(g_), nt(nt_), ns(ns_), ks(ks_), k(k_), has_time(has_time_),
        znssd(znssd_), px(px_), py(py_), dx(dx_), dy(dy_), dt(dt_), frame_off(frame_off_),
        ft(ft_), fnorm(fnorm_), fgx(fgx_), fgy(fgy_), w(w_), ref_rows(ref_rows_),
        motion(motion_), count(count_), w_img(w_img_), h(h_), bt(ks_ * ns_) {
    for (int64_t s = 0; s < ns; ++s)
      for (int64_t q = 0; q < ks; ++q) bt[q * ns + s] = basis[s * ks + q];
    double wsum = 0;
    for (int64_t s = 0; s < ns; ++s) wsum += w[s];
    inv_wsum = T(1.0 / wsum);
  }
};

template <typename T>
struct IcScratch {
  std::vector<T> dxu, dyv, gv, ex, ey, fxs, fys, wy;
  std::vector<int32_t> idx;
  std::vector<double> bb;
  explicit IcScratch(const IcProblem<T>& P)
      : dxu(P.ns), dyv(P.ns), gv(P.ns), ex(P.ns), ey(P.ns), fxs(P.ns), fys(P.ns),
        wy(4 * P.ns), idx(P.ns), bb(2 * P.k) {}
};

// One frame's part of a Ks = 3 row (ic_rhs_row, after sampling g into S.gv) in two passes
// over the subset instead of eleven: (1) the weighted sums of g, g^2 and f g about a shift c
// (a sample of the subset: the sums stay well conditioned whatever the grey level), giving
// g's weighted mean gm, |g - gm|^2 and f.(g - gm); (2) e = w (f - a (g - gm)) and every dot
// product of J^T e at once. Same quantities as the general path, summed in another order.
template <typename T>
inline void frame_sums3(const IcProblem<T>& P, IcScratch<T>& S, const T* fti, const T* gxi,
                        const T* gyi, T swf, double fn, double dti, double* bb, double* zsum,
                        double* bft) {
  const int64_t ns = P.ns, k = P.k;
  const T* w = P.w;
  const T* g = S.gv.data();
  T gm = 0, sgg = 0, sfg = 0;
  if (P.znssd) {
    const T c = g[ns / 2];
    T s1 = 0, s2 = 0, s3 = 0;
#pragma omp simd reduction(+ : s1, s2, s3)
    for (int64_t s = 0; s < ns; ++s) {
      const T d = g[s] - c, wd = w[s] * d;
      s1 += wd;
      s2 += wd * d;
      s3 += wd * fti[s];
    }
    const T md = s1 * P.inv_wsum;  // gm - c
    gm = c + md;
    sgg = s2 - md * s1;            // sum w (g - gm)^2
    sfg = s3 - md * swf;           // sum w f (g - gm), f's own weighted sum swf
  } else {
#pragma omp simd reduction(+ : sgg, sfg)
    for (int64_t s = 0; s < ns; ++s) {
      sgg += w[s] * g[s] * g[s];
      sfg += w[s] * fti[s] * g[s];
    }
  }
  const double gn2 = std::max(double(sgg), 1e-30);
  const double zt = double(sfg) / (fn * std::sqrt(gn2));
  *zsum += zt;
  const T a = P.znssd ? T(fn / std::sqrt(gn2)) : T(1);
  const T ag = a * gm;
  const T* b0 = P.bt.data();
  const T* b1 = b0 + ns;
  const T* b2 = b1 + ns;
  T x0 = 0, x1 = 0, x2 = 0, y0 = 0, y1 = 0, y2 = 0, sx = 0, sy = 0;
#pragma omp simd reduction(+ : x0, x1, x2, y0, y1, y2, sx, sy)
  for (int64_t s = 0; s < ns; ++s) {
    const T e = w[s] * (fti[s] - a * g[s] + ag);
    const T ex = gxi[s] * e, ey = gyi[s] * e;
    x0 += ex * b0[s];
    x1 += ex * b1[s];
    x2 += ex * b2[s];
    y0 += ey * b0[s];
    y1 += ey * b1[s];
    y2 += ey * b2[s];
    sx += ex;
    sy += ey;
  }
  const double bx[3] = {double(x0), double(x1), double(x2)};
  const double by[3] = {double(y0), double(y1), double(y2)};
  for (int q = 0; q < 3; ++q) {
    bb[q] += bx[q];
    bb[k + q] += by[q];
  }
  if (bft) {  // frame t's own (spatial) right-hand side, then its ZNCC
    for (int q = 0; q < 3; ++q) {
      bft[q] = bx[q];
      bft[3 + q] = by[q];
    }
    bft[6] = zt;
  }
  if (P.has_time) {
    bb[k - 1] += dti * double(sx);
    bb[2 * k - 1] += dti * double(sy);
  }
}

// Data row i at parameters pi (2k): b into S.bb (2k, double), the mean ZNCC into *zn, whether
// a warped subset leaves the image into *out; bf (T, 2 Ks + 1) where not null: each frame's
// own spatial b and its ZNCC.
template <typename T, int ORDER>
inline void ic_rhs_row(const IcProblem<T>& P, IcScratch<T>& S, int64_t i, const T* pi, T* zn,
                       bool* out, double* bf) {
  const int64_t nt = P.nt, ns = P.ns, ks = P.ks, k = P.k, np = 2 * k;
  const T* w = P.w;
  const int64_t r = P.ref_rows ? P.ref_rows[i] : i;  // row of the reference subsets
  const T* fti = P.ft + r * ns;
  const T* gxi = P.fgx + r * ns;
  const T* gyi = P.fgy + r * ns;
  T* dxu = S.dxu.data();
  T* dyv = S.dyv.data();
  if (ks == 3) {  // the affine shapes: the warped offsets in one pass
    const T u0 = pi[0], u1 = pi[1], u2 = pi[2], v0 = pi[k], v1 = pi[k + 1], v2 = pi[k + 2];
    const T *b0 = P.bt.data(), *b1 = b0 + ns, *b2 = b1 + ns;
#pragma omp simd
    for (int64_t s = 0; s < ns; ++s) {
      dxu[s] = P.dx[s] + (u0 * b0[s] + u1 * b1[s] + u2 * b2[s]);
      dyv[s] = P.dy[s] + (v0 * b0[s] + v1 * b1[s] + v2 * b2[s]);
    }
  } else {
    std::fill(S.dxu.begin(), S.dxu.end(), T(0));
    std::fill(S.dyv.begin(), S.dyv.end(), T(0));
    for (int64_t q = 0; q < ks; ++q) {
      const T pu = pi[q], pv = pi[k + q];
      const T* bq = P.bt.data() + q * ns;
#pragma omp simd
      for (int64_t s = 0; s < ns; ++s) {
        dxu[s] += pu * bq[s];
        dyv[s] += pv * bq[s];
      }
    }
#pragma omp simd
    for (int64_t s = 0; s < ns; ++s) {
      dxu[s] += P.dx[s];
      dyv[s] += P.dy[s];
    }
  }
  T xmn = dxu[0], xmx = xmn, ymn = dyv[0], ymx = ymn;
#pragma omp simd reduction(min : xmn, ymn) reduction(max : xmx, ymx)
  for (int64_t s = 0; s < ns; ++s) {
    xmn = std::min(xmn, dxu[s]);
    xmx = std::max(xmx, dxu[s]);
    ymn = std::min(ymn, dyv[s]);
    ymx = std::max(ymx, dyv[s]);
  }
  double* bb = S.bb.data();
  std::fill(S.bb.begin(), S.bb.end(), 0.0);
  const double ut = P.has_time ? double(pi[k - 1]) : 0.0;
  const double vt = P.has_time ? double(pi[2 * k - 1]) : 0.0;
  bool out_i = false;
  double zsum = 0;
  const double fn = double(P.fnorm[i]);
  const T swf = P.ks == 3 && P.znssd ? dot(w, fti, ns) : T(0);  // sum w f
  // a window shorter than the call's: its first nti frames, the others padding
  const int64_t nti = P.count ? std::min(std::max(P.count[i], int64_t(1)), nt) : nt;
  if (bf && nti < nt)  // no right-hand side of a padding frame
    std::fill(bf + nti * (2 * ks + 1), bf + nt * (2 * ks + 1),
              std::numeric_limits<double>::quiet_NaN());
  for (int64_t t = 0; t < nti; ++t) {
    const double dti = double(P.dt[i * nt + t]);
    double ox = double(P.px[i]) + ut * dti, oy = double(P.py[i]) + vt * dti;
    if (P.motion) {  // the known (shared) motion of this row's frame t
      ox += double(P.motion[(i * nt + t) * 2]);
      oy += double(P.motion[(i * nt + t) * 2 + 1]);
    }
    out_i = out_i || ox + xmn < 0 || ox + xmx > P.w_img - 1 || oy + ymn < 0 ||
            oy + ymx > P.h - 1;
#if defined(__AVX2__) && defined(__FMA__)
    if constexpr (ORDER == 3 && sizeof(T) == 4)
      cubic_values_f32(P.flat + P.frame_off[i * nt + t], P.g, float(ox), float(oy), dxu, dyv,
                       ns, S.idx.data(), S.fxs.data(), S.wy.data(), S.gv.data());
    else
#endif
      sample_points<T, ORDER>(P.flat + P.frame_off[i * nt + t], P.g, T(ox), T(oy), dxu, dyv,
                              ns, S.idx.data(), S.fxs.data(), S.fys.data(), S.gv.data());
    if (P.ks == 3) {  // the affine shapes: the frame's sums in two fused passes
      frame_sums3<T>(P, S, fti, gxi, gyi, swf, fn, dti, bb, &zsum,
                     bf ? bf + t * (2 * ks + 1) : nullptr);
      continue;
    }
    T gm = 0;
    if (P.znssd) {
      gm = dot(w, S.gv.data(), ns) * P.inv_wsum;
      T* gc = S.gv.data();
#pragma omp simd
      for (int64_t s = 0; s < ns; ++s) gc[s] -= gm;
    }
    // g is now centred (ZNSSD) or raw (SSD)
    T sgg = 0, sfg = 0;
    const T* gc = S.gv.data();
#pragma omp simd reduction(+ : sgg, sfg)
    for (int64_t s = 0; s < ns; ++s) {
      sgg += w[s] * gc[s] * gc[s];
      sfg += w[s] * fti[s] * gc[s];
    }
    const double gn2 = std::max(double(sgg), 1e-30);
    zsum += double(sfg) / (fn * std::sqrt(gn2));
    const T a = P.znssd ? T(fn / std::sqrt(gn2)) : T(1);
    T* exp_ = S.ex.data();
    T* eyp = S.ey.data();
#pragma omp simd
    for (int64_t s = 0; s < ns; ++s) {
      const T e = w[s] * (fti[s] - a * gc[s]);
      exp_[s] = gxi[s] * e;
      eyp[s] = gyi[s] * e;
    }
    double* bft = bf ? bf + t * (2 * ks + 1) : nullptr;
    for (int64_t q = 0; q < ks; ++q) {
      const double bxq = double(dot(exp_, P.bt.data() + q * ns, ns));
      const double byq = double(dot(eyp, P.bt.data() + q * ns, ns));
      bb[q] += bxq;
      bb[k + q] += byq;
      if (bft) {  // frame t's own (spatial) right-hand side: a classical step's
        bft[q] = bxq;
        bft[ks + q] = byq;
      }
    }
    if (bft) bft[2 * ks] = double(sfg) / (fn * std::sqrt(gn2));  // and frame t's ZNCC
    if (P.has_time) {
      T sx = 0, sy = 0;
#pragma omp simd reduction(+ : sx, sy)
      for (int64_t s = 0; s < ns; ++s) {
        sx += exp_[s];
        sy += eyp[s];
      }
      bb[k - 1] += dti * double(sx);
      bb[2 * k - 1] += dti * double(sy);
    }
  }
  (void)np;
  *zn = T(zsum / double(nti));
  *out = out_i;
}

template <typename T, int ORDER>
void ic_rhs_range(const IcProblem<T>& P, int64_t i0, int64_t i1, const T* p,
                  const int64_t* rows, double* b, T* zn, uint8_t* outside, double* bframe) {
  const int64_t np = 2 * P.k, nt = P.nt, ks = P.ks;
  IcScratch<T> S(P);
  for (int64_t j = i0; j < i1; ++j) {
    // j: position in p and the outputs; i: row of the per-point data
    const int64_t i = rows ? rows[j] : j;
    bool out_i = false;
    ic_rhs_row<T, ORDER>(P, S, i, p + j * np, zn + j, &out_i,
                         bframe ? bframe + j * nt * (2 * ks + 1) : nullptr);
    for (int64_t q = 0; q < np; ++q) b[j * np + q] = S.bb[q];
    outside[j] = out_i ? 1 : 0;
  }
}

// Weighted Gram matrix of the augmented steepest-descent images of each POI:
//   J_s = [gx B_0 .. gx B_{ks-1}, gx, gy B_0 .. gy B_{ks-1}, gy]   (P' = 2 (ks + 1))
//   G = sum_s w J_s J_s^T  (N, P', P'),  m = sum_s w J_s  (N, P')   in double.
STS_KERNEL(sts_gram, (int64_t i0, int64_t i1, int64_t ns, int64_t ks, const T* gx,
                      const T* gy, const T* basis, const T* w, double* G, double* m)) {
  // G's entries are sum_s w b_q b_r g_c g_d (b_q: basis column q or the constant 1; g_c:
  // gx or gy): the window-weighted basis products (once per call) dotted with the three
  // gradient products (once per point), 3 per basis pair instead of one per entry
  const int64_t na = ks + 1, np = 2 * na;
  std::vector<T> wb(na * ns), wbb(na * na * ns), gg(3 * ns);
  for (int64_t s = 0; s < ns; ++s) {
    for (int64_t q = 0; q < ks; ++q) wb[q * ns + s] = w[s] * basis[s * ks + q];
    wb[ks * ns + s] = w[s];
  }
  for (int64_t q = 0; q < na; ++q)
    for (int64_t r = q; r < na; ++r)
      for (int64_t s = 0; s < ns; ++s)
        wbb[(q * na + r) * ns + s] = wb[q * ns + s] * (r < ks ? basis[s * ks + r] : T(1));
  T* gxx = gg.data();
  T* gxy = gxx + ns;
  T* gyy = gxy + ns;
  for (int64_t i = i0; i < i1; ++i) {
    const T* gxi = gx + i * ns;
    const T* gyi = gy + i * ns;
#pragma omp simd
    for (int64_t s = 0; s < ns; ++s) {
      gxx[s] = gxi[s] * gxi[s];
      gxy[s] = gxi[s] * gyi[s];
      gyy[s] = gyi[s] * gyi[s];
    }
    double* Gi = G + i * np * np;
    double* mi = m + i * np;
    for (int64_t q = 0; q < na; ++q) {
      mi[q] = double(dot(wb.data() + q * ns, gxi, ns));
      mi[na + q] = double(dot(wb.data() + q * ns, gyi, ns));
      for (int64_t r = q; r < na; ++r) {
        const T* wqr = wbb.data() + (q * na + r) * ns;
        const double xx = double(dot(wqr, gxx, ns));
        const double xy = double(dot(wqr, gxy, ns));
        const double yy = double(dot(wqr, gyy, ns));
        Gi[q * np + r] = Gi[r * np + q] = xx;
        Gi[(na + q) * np + na + r] = Gi[(na + r) * np + na + q] = yy;
        Gi[q * np + na + r] = Gi[(na + r) * np + q] = xy;
        Gi[r * np + na + q] = Gi[(na + q) * np + r] = xy;
      }
    }
  }
  return 0;
}

// The joint IC-GN right-hand side b (M, 2k) in double, the mean ZNCC zn and the outside flag
// of the rows j in [i0, i1) of p (see ic_rhs_range); rows[j] is row j's per-point data row
// (rows null: row j); ref_rows[i] is data row i's row of the reference subsets ft, gx, gy
// (points repeated over targets share theirs; null: row i); motion (N, T, 2) a known
// displacement (u, v) added to the warp of each data row's frame t (the shared motion of the
// specimen; null: none); bframe (M, T, 2 Ks + 1) in double, where not null, each frame's own
// spatial part of b (the classical IC-GN right-hand side of frame t at this warp), then the
// frame's ZNCC there.
STS_KERNEL(sts_ic_rhs, (const T* flat, int64_t wp, double x_lo, double x_hi, double y_lo,
                        double y_hi, int64_t shift, int order, int64_t i0, int64_t i1,
                        int64_t nt, int64_t ns, int64_t ks, int64_t k, int has_time, int znssd,
                        const T* p, const T* px, const T* py, const T* dx, const T* dy,
                        const T* basis, const T* dt, const int64_t* frame_off, const T* ft,
                        const T* fnorm, const T* gx, const T* gy, const T* w,
                        nullable<const int64_t> rows, nullable<const int64_t> ref_rows,
                        nullable<const T> motion, nullable<const int64_t> count, double w_img,
                        double h, double* b, T* zn, uint8_t* outside,
                        nullable<double> bframe)) {
  const Geo g{wp, x_lo, x_hi, y_lo, y_hi, shift};
  if (order != 3 && order != 5) return 1;
  const IcProblem<T> P(flat, g, nt, ns, ks, k, has_time != 0, znssd != 0, px, py, dx, dy, basis,
                       dt, frame_off, ft, fnorm, gx, gy, w, ref_rows, motion, count, w_img,
                       h);
  if (order == 3)
    ic_rhs_range<T, 3>(P, i0, i1, p, rows, b, zn, outside, bframe);
  else
    ic_rhs_range<T, 5>(P, i0, i1, p, rows, b, zn, outside, bframe);
  return 0;
}

// ---- the joint IC-GN solve, point by point ------------------------------------------------
// core/gauss_newton.py's stage loop for one point at a time: each thread takes `chunk` points
// from a shared counter and iterates every one of them to its end, with no barrier between
// iterations (a descheduled thread holds back only its own chunk). Per iteration, as there:
//   b, zn, outside = ic_rhs_row(p);  dp = -(Hinv b) (double, then T);
//   p_new = p o dp^-1 (affine_compose);  norm = |dp * scale|;
//   finite = norm and p_new finite;  bad = !finite or norm > div_norm;
//   rate = clamp(prev > 0 ? norm / prev : 1, rate_floor, 1);
//   converged = finite and norm * rate < tol and !outside;  prev = norm;
//   p = p_new where finite;  ends on converged, bad or outside (status diverged/outside/
//   converged), else after max_iter iterations (status max_iter; p the last iterate).

// W(p) o W(dp)^-1 of the affine (spatio-temporal) warp, in T, as shape.AffineShape's
// compose_inverse: M = (I + D)(I + dD)^-1, b' = b - M db, bt' = bt - M dbt.
template <typename T>
inline void affine_compose(const T* p, const T* dp, int64_t k, bool has_time, T* out) {
  const T a00 = T(1) + dp[1], a01 = dp[2], a10 = dp[k + 1], a11 = T(1) + dp[k + 2];
  const T det = a00 * a11 - a01 * a10;
  const T i00 = a11 / det, i01 = -a01 / det, i10 = -a10 / det, i11 = a00 / det;
  const T e00 = T(1) + p[1], e01 = p[2], e10 = p[k + 1], e11 = T(1) + p[k + 2];
  const T m00 = e00 * i00 + e01 * i10, m01 = e00 * i01 + e01 * i11;
  const T m10 = e10 * i00 + e11 * i10, m11 = e10 * i01 + e11 * i11;
  const T bu = p[0] - (m00 * dp[0] + m01 * dp[k]);
  const T bv = p[k] - (m10 * dp[0] + m11 * dp[k]);
  out[0] = bu;
  out[1] = m00 - T(1);
  out[2] = m01;
  out[k] = bv;
  out[k + 1] = m10;
  out[k + 2] = m11 - T(1);
  if (has_time) {
    out[3] = p[3] - (m00 * dp[3] + m01 * dp[k + 3]);
    out[k + 3] = p[k + 3] - (m10 * dp[3] + m11 * dp[k + 3]);
  }
}

template <typename T, int ORDER>
void ic_solve_points(const IcProblem<T>& P, int64_t i0, int64_t i1, int64_t* counter,
                     int64_t chunk, const double* hinv, const T* scale, T* p, const T* prev0,
                     double tol, int64_t max_iter, double div_norm, double rate_floor,
                     const int64_t* codes, T* zn, uint8_t* status, int32_t* used,
                     double* bframe, T* plast) {
  const int64_t np = 2 * P.k, nt = P.nt, fw = 2 * P.ks + 1;
  IcScratch<T> S(P);
  std::vector<T> dp(np), pn(np), pold(np);
  const T nan = std::numeric_limits<T>::quiet_NaN();
  for (;;) {
    const int64_t c0 = i0 + __atomic_fetch_add(counter, chunk, __ATOMIC_RELAXED);
    if (c0 >= i1) break;
    const int64_t c1 = std::min(i1, c0 + chunk);
    for (int64_t i = c0; i < c1; ++i) {
      T* pi = p + i * np;
      const double* hi = hinv + i * np * np;
      const T* sc = scale + i * np;
      double* bf = bframe ? bframe + i * nt * fw : nullptr;
      T prev = prev0[i], znv = nan;
      int64_t st = codes[1], it = 0;
      while (it < max_iter) {
        bool out_i = false;
        ic_rhs_row<T, ORDER>(P, S, i, pi, &znv, &out_i, bf);
        const double* bb = S.bb.data();
        for (int64_t a = 0; a < np; ++a) {
          double acc = 0.0;
          for (int64_t c = 0; c < np; ++c) acc += hi[a * np + c] * bb[c];
          dp[a] = T(-acc);
        }
        affine_compose(pi, dp.data(), P.k, P.has_time, pn.data());
        ++it;
        T n2 = 0;
        bool finite = true;
        for (int64_t a = 0; a < np; ++a) {
          const T d = dp[a] * sc[a];
          n2 += d * d;
          finite = finite && std::isfinite(pn[a]);
        }
        const T norm = std::sqrt(n2);
        finite = finite && std::isfinite(norm);
        const bool bad = !finite || norm > T(div_norm);  // compared in T, as torch does
        T rate = prev > T(0) ? norm / prev : T(1);
        rate = std::min(std::max(rate, T(rate_floor)), T(1));
        const bool conv = finite && norm * rate < T(tol) && !out_i;
        prev = norm;
        if (plast) std::copy(pi, pi + np, pold.begin());
        if (finite) std::copy(pn.begin(), pn.end(), pi);
        if (conv || bad || out_i) {
          st = bad ? codes[2] : (out_i ? codes[3] : codes[0]);
          if (plast) std::copy(pold.begin(), pold.end(), plast + i * np);
          break;
        }
      }
      if (st == codes[1]) {  // no step ended the point: no last step to report
        if (bf) std::fill(bf, bf + nt * fw, std::numeric_limits<double>::quiet_NaN());
        if (plast) std::fill(plast + i * np, plast + (i + 1) * np, nan);
      }
      zn[i] = znv;
      status[i] = uint8_t(st);
      used[i] = int32_t(it);
    }
  }
}

// Each point i in [i0, i1) solved to its end (see ic_solve_points), threads taking `chunk`
// points at a time from *counter (set to 0 before the call; every thread of a call runs this
// with the same arguments). The problem's arguments are sts_ic_rhs's (the data rows are p's
// rows); hinv (N, P, P) double, the inverse Hessians; scale (N, P) the increments' scale;
// p (N, P) the start, overwritten by the result; prev (N,) the previous increments (0: none);
// codes: the statuses converged, max_iter, diverged, outside. Out: zn (N,) the mean ZNCC of
// the last step, status (N,), used (N,) the iterations; bframe (N, T, 2 Ks + 1) and plast
// (N, P), where not null, the last step's frame-by-frame b and ZNCC and the parameters it was
// taken at (NaN where the point ran out of iterations). Affine shapes only (Ks = 3).
STS_KERNEL(sts_ic_solve, (const T* flat, int64_t wp, double x_lo, double x_hi, double y_lo,
                          double y_hi, int64_t shift, int order, int64_t i0, int64_t i1,
                          int64_t* counter, int64_t chunk, int64_t nt, int64_t ns, int64_t ks,
                          int64_t k, int has_time, int znssd, const T* px, const T* py,
                          const T* dx, const T* dy, const T* basis, const T* dt,
                          const int64_t* frame_off, const T* ft, const T* fnorm, const T* gx,
                          const T* gy, const T* w, nullable<const int64_t> ref_rows,
                          nullable<const T> motion, nullable<const int64_t> count,
                          double w_img, double h,
                          const double* hinv, const T* scale, T* p, const T* prev, double tol,
                          int64_t max_iter, double div_norm, double rate_floor,
                          const int64_t* codes, T* zn, uint8_t* status, int32_t* used,
                          nullable<double> bframe, nullable<T> plast)) {
  if (order != 3 && order != 5) return 1;
  if (ks != 3 || k != ks + (has_time ? 1 : 0) || chunk < 1) return 2;
  const Geo g{wp, x_lo, x_hi, y_lo, y_hi, shift};
  const IcProblem<T> P(flat, g, nt, ns, ks, k, has_time != 0, znssd != 0, px, py, dx, dy, basis,
                       dt, frame_off, ft, fnorm, gx, gy, w, ref_rows, motion, count, w_img,
                       h);
  if (order == 3)
    ic_solve_points<T, 3>(P, i0, i1, counter, chunk, hinv, scale, p, prev, tol, max_iter,
                          div_norm, rate_floor, codes, zn, status, used, bframe, plast);
  else
    ic_solve_points<T, 5>(P, i0, i1, counter, chunk, hinv, scale, p, prev, tol, max_iter,
                          div_norm, rate_floor, codes, zn, status, used, bframe, plast);
  return 0;
}

// ---- small symmetric positive definite inverses ------------------------------------------
// inv (np, np) = a^-1 of the symmetric positive definite (np, np) matrix a (its lower
// triangle read), by Cholesky: a = L L^T, inv = L^-T L^-1, in double; false (inv unset)
// where a is not positive definite (a pivot not > 0, or not finite). np <= 16.
template <typename A>
inline bool cholesky_inverse(const A* a, int64_t np, double* inv) {
  double L[256], M[256];
  for (int64_t j = 0; j < np; ++j) {
    double d = double(a[j * np + j]);
    for (int64_t k = 0; k < j; ++k) d -= L[j * np + k] * L[j * np + k];
    if (!(d > 0.0) || !std::isfinite(d)) return false;
    const double ljj = std::sqrt(d);
    L[j * np + j] = ljj;
    for (int64_t r = j + 1; r < np; ++r) {
      double v = double(a[r * np + j]);
      for (int64_t k = 0; k < j; ++k) v -= L[r * np + k] * L[j * np + k];
      L[r * np + j] = v / ljj;
    }
  }
  for (int64_t c = 0; c < np; ++c) {  // M = L^-1 (lower), column by column
    for (int64_t r = c; r < np; ++r) {
      double v = r == c ? 1.0 : 0.0;
      for (int64_t k = c; k < r; ++k) v -= L[r * np + k] * M[k * np + c];
      M[r * np + c] = v / L[r * np + r];
    }
  }
  for (int64_t p = 0; p < np; ++p) {  // inv = M^T M
    for (int64_t q = p; q < np; ++q) {
      double v = 0.0;
      for (int64_t r = q; r < np; ++r) v += M[r * np + p] * M[r * np + q];
      inv[p * np + q] = inv[q * np + p] = v;
    }
  }
  return true;
}

// The inverse of each symmetric positive definite (np, np) matrix h[i] (its lower triangle
// read) of the rows [i0, i1) (cholesky_inverse); bad[i] = 1 and inv[i] NaN where h[i] is not
// positive definite. np <= 16 (the Hessians and noise responses: 6 to 12 parameters).
// torch's batched cholesky_ex + cholesky_inverse take ~15 ms for 38,809 6x6 matrices, this
// ~1 ms.
STS_KERNEL(sts_spd_inverse, (int64_t i0, int64_t i1, int64_t np, const T* h, T* inv,
                             uint8_t* bad)) {
  if (np < 1 || np > 16) return 1;
  for (int64_t i = i0; i < i1; ++i) {
    T* out = inv + i * np * np;
    double v[256];
    if (!cholesky_inverse(h + i * np * np, np, v)) {
      for (int64_t q = 0; q < np * np; ++q) out[q] = std::numeric_limits<T>::quiet_NaN();
      bad[i] = 1;
      continue;
    }
    for (int64_t q = 0; q < np * np; ++q) out[q] = T(v[q]);
    bad[i] = 0;
  }
  return 0;
}

// ---- predicted standard deviations of the parameters -------------------------------------
// uncertainty.std_of(uncertainty.response(...)) row by row, without the (N, P', P')
// temporaries. Row i: z_t = (1 .. 1, dt_t) per component (dt_t at the augmented columns ks
// and 2 ks + 1 where has_time, else 0), zz = sum_t z_t z_t^T, zs = sum_t z_t, each
// restricted to the parameters' augmented columns cols[0 .. np); with f = f2[i] (reference
// noise variance) and g = g2n[i] (one frame's):
//   A = g1 o zz - kappa f bw o zz   (Cholesky; g1 o zz where A is not positive definite;
//                                    std NaN where neither is)
//   M = f g2 o zs zs^T + g g2 o zz + kappa f g b2 o zz
//   std_p = sqrt(max(0, (A^-1 M A^-1)_pp)).
// g1, g2 (npa, npa) per row (g2 null: g1, a 0/1 window), bw, b2 (npa, npa) shared; np <= 16.
STS_KERNEL(sts_param_std, (int64_t i0, int64_t i1, int64_t npa, int64_t np, int64_t nt,
                           int64_t ks, int64_t has_time, const int64_t* cols, const T* dt,
                           nullable<const int64_t> count, const T* g1, nullable<const T> g2, const T* bw, const T* b2,
                           const T* f2, const T* g2n, double kappa, T* std)) {
  if (np < 1 || np > 16 || npa < np) return 1;
  for (int64_t a = 0; a < np; ++a) {
    if (cols[a] < 0 || cols[a] >= npa) return 2;
  }
  for (int64_t i = i0; i < i1; ++i) {
    double s1 = 0.0, s2 = 0.0;
    const int64_t nti = count ? std::min(std::max(count[i], int64_t(1)), nt) : nt;
    if (has_time) {
      for (int64_t t = 0; t < nti; ++t) {
        const double d = double(dt[i * nt + t]);
        s1 += d;
        s2 += d * d;
      }
    }
    const double s0 = double(nti);
    bool tm[16];
    for (int64_t a = 0; a < np; ++a) tm[a] = has_time && (cols[a] == ks || cols[a] == 2 * ks + 1);
    const T* G1 = g1 + i * npa * npa;
    const T* G2 = g2 ? g2 + i * npa * npa : G1;
    const double f = double(f2[i]), g = double(g2n[i]);
    double A[256], H[256], M[256], inv[256];
    for (int64_t a = 0; a < np; ++a) {
      const double za = tm[a] ? s1 : s0;
      for (int64_t b = 0; b < np; ++b) {
        const double zb = tm[b] ? s1 : s0;
        const double zz = tm[a] && tm[b] ? s2 : (tm[a] || tm[b] ? s1 : s0);
        const int64_t e = cols[a] * npa + cols[b];
        const double h = double(G1[e]) * zz;
        H[a * np + b] = h;
        A[a * np + b] = h - kappa * f * double(bw[e]) * zz;
        M[a * np + b] = f * double(G2[e]) * za * zb + g * double(G2[e]) * zz
                        + kappa * f * g * double(b2[e]) * zz;
      }
    }
    T* out = std + i * np;
    if (!cholesky_inverse(A, np, inv) && !cholesky_inverse(H, np, inv)) {
      for (int64_t p = 0; p < np; ++p) out[p] = std::numeric_limits<T>::quiet_NaN();
      continue;
    }
    for (int64_t p = 0; p < np; ++p) {
      double var = 0.0;
      for (int64_t a = 0; a < np; ++a) {
        double ma = 0.0;
        for (int64_t b = 0; b < np; ++b) ma += M[a * np + b] * inv[b * np + p];
        var += inv[a * np + p] * ma;
      }
      out[p] = T(std::sqrt(std::max(var, 0.0)));
    }
  }
  return 0;
}

// ---- medians of short rows ---------------------------------------------------------------
// the median of the c values v[0..c) (sorted in place; v has room for 8): the lower middle
// one; NaN if c == 0. Up to 8 values: padded with +inf (sorted last) and sorted by a
// branch-free sorting network (19 compare-exchanges); more: by insertion
template <typename T>
inline T lower_median(T* v, int c) {
  if (c <= 8) {
    constexpr int net[19][2] = {{0, 1}, {2, 3}, {4, 5}, {6, 7}, {0, 2}, {1, 3}, {4, 6},
                                {5, 7}, {1, 2}, {5, 6}, {0, 4}, {3, 7}, {1, 5}, {2, 6},
                                {1, 4}, {3, 6}, {2, 4}, {3, 5}, {3, 4}};
    for (int j = c; j < 8; ++j) v[j] = std::numeric_limits<T>::infinity();
    for (const auto& e : net) {
      const T a = v[e[0]], b = v[e[1]];
      v[e[0]] = std::min(a, b);
      v[e[1]] = std::max(a, b);
    }
    return c ? v[(c - 1) / 2] : std::numeric_limits<T>::quiet_NaN();
  }
  for (int j = 1; j < c; ++j) {  // insertion sort (c <= 64)
    const T a = v[j];
    int q = j;
    while (q > 0 && v[q - 1] > a) {
      v[q] = v[q - 1];
      --q;
    }
    v[q] = a;
  }
  return c ? v[(c - 1) / 2] : std::numeric_limits<T>::quiet_NaN();
}

// The median of each row [i0, i1) of x (rows of k <= 64 values) over its values that are not
// NaN, the lower of the two middle ones for an even count (torch.nanmedian's), NaN where a row
// has none. The neighbour test takes it over a point's k = 8 neighbours, 10^5 rows at a time:
// torch's batched nanmedian costs ~9 ms per 155,000 rows, this 1.5 ms (2 threads).
STS_KERNEL(sts_nanmedian, (int64_t i0, int64_t i1, int64_t k, const T* x, T* out)) {
  if (k < 1 || k > 64) return 1;
  T v[64];
  for (int64_t i = i0; i < i1; ++i) {
    const T* xi = x + i * k;
    int c = 0;
    for (int64_t j = 0; j < k; ++j)
      if (xi[j] == xi[j]) v[c++] = xi[j];
    out[i] = lower_median(v, c);
  }
  return 0;
}

// ---- Immerkaer's noise estimate (core/noise.py, immerkaer_sigmas) -------------------------
// The "valid" 3x3 stencils of pixel (i, j) of a frame p (h x w, row-major) as noise.py forms
// them from its 1-D factors, in T, each operation in its order (2 x a value is exact, so a
// fused multiply-add rounds as the separate operations do): Sobel's |d/dx| + |d/dy| and the
// Laplacian difference's magnitude, at output pixel (i, j) of (h - 2) x (w - 2).
template <typename T>
inline T sobel_at(const T* p, int64_t w, int64_t i, int64_t j) {
  const T* r0 = p + i * w + j;
  const T *r1 = r0 + w, *r2 = r1 + w;
  const T sx = ((r0[2] - r0[0]) + T(2) * (r1[2] - r1[0])) + (r2[2] - r2[0]);
  const T sy = ((r2[0] - r0[0]) + T(2) * (r2[1] - r0[1])) + (r2[2] - r0[2]);
  return std::abs(sx) + std::abs(sy);
}

template <typename T>
inline T laplacian_at(const T* p, int64_t w, int64_t i, int64_t j) {
  const T* r0 = p + i * w + j;
  const T *r1 = r0 + w, *r2 = r1 + w;
  const T l0 = (r0[0] - T(2) * r0[1]) + r0[2];
  const T l1 = (r1[0] - T(2) * r1[1]) + r1[2];
  const T l2 = (r2[0] - T(2) * r2[1]) + r2[2];
  return std::abs((l0 - T(2) * l1) + l2);
}

// Frames f in [i0, i1) of x (F, h, w) of whole-number grey levels (the caller checks, and
// that 8 x their range stays below bins): counts[f * bins + g] += 1 for Sobel's magnitude g at
// every step-th output pixel (row-major over the (h - 2) x (w - 2), from the first: a
// strided row of the flattened magnitudes, as noise.py subsamples them).
STS_KERNEL(sts_sobel_counts, (int64_t i0, int64_t i1, const T* x, int64_t h, int64_t w,
                              int64_t step, int64_t bins, int64_t* counts)) {
  if (h < 3 || w < 3 || step < 1) return 1;
  const int64_t wv = w - 2, nv = (h - 2) * wv;
  for (int64_t f = i0; f < i1; ++f) {
    const T* p = x + f * h * w;
    int64_t* c = counts + f * bins;
    int64_t i = 0, j = 0;  // output pixel k = i * wv + j
    for (int64_t k = 0; k < nv; k += step) {
      const int64_t g = int64_t(sobel_at(p, w, i, j));
      if (g < 0 || g >= bins) return 2;
      ++c[g];
      for (j += step; j >= wv; j -= wv) ++i;
    }
  }
  return 0;
}

// Frames f in [i0, i1) of x (F, h, w) of whole-number grey levels: the Laplacian difference's
// magnitudes summed (sums[f], exact in double) and counted (kept[f]) over the output pixels
// whose Sobel magnitude is at most cut[f] (noise.py's mean of the flat pixels).
STS_KERNEL(sts_flat_sums, (int64_t i0, int64_t i1, const T* x, int64_t h, int64_t w,
                           const T* cut, double* sums, int64_t* kept)) {
  if (h < 3 || w < 3) return 1;
  for (int64_t f = i0; f < i1; ++f) {
    const T* p = x + f * h * w;
    const T c = cut[f];
    int64_t s = 0, n = 0;  // whole numbers: summed exactly, in any order (branch-free)
    for (int64_t i = 0; i < h - 2; ++i)
      for (int64_t j = 0; j < w - 2; ++j) {
        const bool flat = sobel_at(p, w, i, j) <= c;
        s += flat ? int64_t(laplacian_at(p, w, i, j)) : 0;
        n += flat;
      }
    sums[f] = double(s);
    kept[f] = n;
  }
  return 0;
}

// ---- the neighbour test (quality.median_test) -------------------------------------------
// One round of the normalised median test of quality.py, per point, over its k <= 64 grid
// neighbours: the same arithmetic as the torch code (quality.carried_neighbours and
// median_test), in double, each product and sum rounded on its own (no fused multiply-add,
// see exact_mul_add), so both give the same decisions. Rows r = b * n + i: target b, point i.

// a * b + c with the product rounded before the sum, as torch computes it (this file is
// built with -ffp-contract=fast, which would fuse them; sts_nb_test rounds its products
// through volatile temporaries for the same reason)
inline double exact_mul_add(double a, double b, double c) {
  volatile double t = a * b;
  return t + c;
}

// Whether a point's own gradient is like its neighbours' (quality.carried_neighbours):
// own[r, e] = valid[r] and |g[r, e] - med| <= 3 mad + tol, med and mad the median and the
// median absolute deviation of component e (of nc x 2) over the valid neighbours' gradients.
STS_KERNEL(sts_nb_own, (int64_t i0, int64_t i1, int64_t n, int64_t k, int64_t ne,
                        const int64_t* nb, const uint8_t* valid, const T* g, double tol,
                        uint8_t* own)) {
  if (k < 1 || k > 64 || ne < 1 || ne > 16 || n < 1) return 1;
  int64_t use[64];
  T v[64];
  for (int64_t r = i0; r < i1; ++r) {
    const int64_t b = r / n, i = r - b * n;
    int cu = 0;
    if (valid[r]) {
      for (int64_t j = 0; j < k; ++j) {
        const int64_t q = nb[i * k + j];
        if (q >= 0 && q < n && valid[b * n + q]) use[cu++] = b * n + q;
      }
    }
    for (int64_t e = 0; e < ne; ++e) {
      uint8_t ok = 0;
      if (cu) {
        int c = 0;
        for (int u = 0; u < cu; ++u) {
          const T x = g[use[u] * ne + e];
          if (x == x) v[c++] = x;
        }
        const T med = lower_median(v, c);
        for (int u = 0; u < c; ++u) v[u] = std::fabs(v[u] - med);
        const T mad = lower_median(v, c);
        const double x = double(g[r * ne + e]);
        ok = std::fabs(x - double(med)) <= exact_mul_add(3.0, double(mad), tol);
      }
      own[r * ne + e] = ok;
    }
  }
  return 0;
}

// The test's numbers for each point: its valid neighbours' values v (nc components), carried
// to the point by the trapezoid rule with their gradients g and the gradient at the point
// `at` (both (rows, nc, 2); null: not carried), d = p[i] - p[q]:
//   vn = v[q] + (0.5 (g[q] + at[r]))_x d_x + (0.5 (g[q] + at[r]))_y d_y  (NaN g[q] as 0);
// med, rm: per component the median of vn and of |vn - med| (lower middle, NaN values left
// out); out_r = max over components of |v[r] - med| / (rm + eps[r]) (NaN if any is NaN);
// out_rm (rows, nc); out_count: the neighbours whose first component is a number.
STS_KERNEL(sts_nb_test, (int64_t i0, int64_t i1, int64_t n, int64_t k, int64_t nc,
                         const int64_t* nb, const uint8_t* valid, const T* v, const T* p,
                         nullable<const T> g, nullable<const T> at, const T* eps, T* out_r,
                         T* out_rm, int64_t* out_count)) {
  if (k < 1 || k > 64 || nc < 1 || nc > 8 || n < 1) return 1;
  const T big = std::numeric_limits<T>::max();
  T vn[8][64];
  T w[64];
  for (int64_t r = i0; r < i1; ++r) {
    const int64_t b = r / n, i = r - b * n;
    int cu = 0;
    for (int64_t j = 0; j < k; ++j) {
      const int64_t q = nb[i * k + j];
      if (q < 0 || q >= n || !valid[b * n + q]) continue;
      const int64_t rq = b * n + q;
      const T dx = p[i * 2] - p[q * 2], dy = p[i * 2 + 1] - p[q * 2 + 1];
      for (int64_t c = 0; c < nc; ++c) {
        T x = v[rq * nc + c];
        if (g != nullptr && at != nullptr) {
          T gx = g[(rq * nc + c) * 2], gy = g[(rq * nc + c) * 2 + 1];
          gx = gx != gx ? T(0) : (gx > big ? big : (gx < -big ? -big : gx));  // nan_to_num
          gy = gy != gy ? T(0) : (gy > big ? big : (gy < -big ? -big : gy));
          volatile T tx = (T(0.5) * (gx + at[(r * nc + c) * 2])) * dx;
          volatile T ty = (T(0.5) * (gy + at[(r * nc + c) * 2 + 1])) * dy;
          const T t = tx + ty;
          x = x + t;
        }
        vn[c][cu] = x;
      }
      ++cu;
    }
    int64_t count = 0;
    for (int u = 0; u < cu; ++u) count += vn[0][u] == vn[0][u];
    T rmax = T(0);
    bool any_nan = false;
    for (int64_t c = 0; c < nc; ++c) {
      int m = 0;
      for (int u = 0; u < cu; ++u)
        if (vn[c][u] == vn[c][u]) w[m++] = vn[c][u];
      const T med = lower_median(w, m);
      for (int u = 0; u < m; ++u) w[u] = std::fabs(w[u] - med);
      const T rm = lower_median(w, m);
      out_rm[r * nc + c] = rm;
      const T q = std::fabs(v[r * nc + c] - med) / (rm + eps[r]);
      if (q != q) any_nan = true;
      else if (c == 0 || q > rmax) rmax = q;
    }
    out_r[r] = any_nan ? std::numeric_limits<T>::quiet_NaN() : rmax;
    out_count[r] = count;
  }
  return 0;
}

// ---- B-spline prefilter: recursive (Unser 1991; Thevenaz's initialisation) -----------------
// Mirror (whole-sample symmetric) boundary, the same as interpolation.bspline_prefilter's
// FFT version, to ~1e-12 relative in double.

inline int poles(int order, double* z) {
  if (order == 3) {
    z[0] = std::sqrt(3.0) - 2.0;
    return 1;
  }
  z[0] = std::sqrt(135.0 / 2.0 - std::sqrt(17745.0 / 4.0)) + std::sqrt(105.0 / 4.0) - 6.5;
  z[1] = std::sqrt(135.0 / 2.0 + std::sqrt(17745.0 / 4.0)) - std::sqrt(105.0 / 4.0) - 6.5;
  return 2;
}

// Filter `m` interleaved lines at once: element k of line j is at c[k * stride + j]
// (stride = m for columns of a plane, a single line with m = 1 otherwise); n samples each.
template <typename T>
void recursive_lines(T* c, int64_t n, int64_t m, int64_t stride, int order) {
  if (n < 2) return;
  double z[2];
  const int np = poles(order, z);
  double gain = 1.0;
  for (int q = 0; q < np; ++q) gain *= (1.0 - z[q]) * (1.0 - 1.0 / z[q]);
  std::vector<double> acc(m);
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < m; ++j) c[k * stride + j] = T(c[k * stride + j] * gain);
  for (int q = 0; q < np; ++q) {
    const double zq = z[q];
    // causal initial value: sum_k z^k c[k] over the mirrored signal
    const int64_t horizon = int64_t(std::ceil(std::log(1e-13) / std::log(std::fabs(zq))));
    if (horizon < n) {
      for (int64_t j = 0; j < m; ++j) acc[j] = c[j];
      double zn = zq;
      for (int64_t k = 1; k < horizon; ++k) {
        for (int64_t j = 0; j < m; ++j) acc[j] += zn * c[k * stride + j];
        zn *= zq;
      }
    } else {
      double zn = zq;
      const double iz = 1.0 / zq;
      double z2n = std::pow(zq, double(n - 1));
      for (int64_t j = 0; j < m; ++j) acc[j] = c[j] + z2n * c[(n - 1) * stride + j];
      z2n *= z2n * iz;
      for (int64_t k = 1; k <= n - 2; ++k) {
        for (int64_t j = 0; j < m; ++j) acc[j] += (zn + z2n) * c[k * stride + j];
        zn *= zq;
        z2n *= iz;
      }
      for (int64_t j = 0; j < m; ++j) acc[j] /= (1.0 - zn * zn);
    }
    for (int64_t j = 0; j < m; ++j) c[j] = T(acc[j]);
    for (int64_t k = 1; k < n; ++k) {
      T* ck = c + k * stride;
      const T* cp = c + (k - 1) * stride;
      const T zt = T(zq);
#pragma omp simd
      for (int64_t j = 0; j < m; ++j) ck[j] += zt * cp[j];
    }
    // anti-causal initial value
    {
      T* cl = c + (n - 1) * stride;
      const T* cm = c + (n - 2) * stride;
      const double f = zq / (zq * zq - 1.0);
      for (int64_t j = 0; j < m; ++j) cl[j] = T(f * (zq * cm[j] + cl[j]));
    }
    for (int64_t k = n - 2; k >= 0; --k) {
      T* ck = c + k * stride;
      const T* cn = c + (k + 1) * stride;
      const T zt = T(zq);
#pragma omp simd
      for (int64_t j = 0; j < m; ++j) ck[j] = zt * (cn[j] - ck[j]);
    }
  }
}

// rows [i0, i1) of a (P*H, W) stack along W (axis 1), or column blocks [i0, i1) of the
// P planes along H (axis 0: block b covers columns [b*64, b*64+64) of plane b / nb)
STS_KERNEL(sts_prefilter, (T* data, int64_t planes, int64_t h, int64_t w, int order, int axis,
                           int64_t i0, int64_t i1)) {
  if (order != 3 && order != 5) return 1;
  if (axis == 1) {
    for (int64_t r = i0; r < i1; ++r) recursive_lines(data + r * w, w, int64_t(1), int64_t(1),
                                                      order);
    return 0;
  }
  const int64_t bw = 64, nb = (w + bw - 1) / bw;
  for (int64_t b = i0; b < i1; ++b) {
    const int64_t plane = b / nb, c0 = (b % nb) * bw;
    const int64_t m = std::min(bw, w - c0);
    recursive_lines(data + plane * h * w + c0, h, m, w, order);
  }
  (void)planes;
  return 0;
}

// ---- the template's samples (movie/template_image.splat) ---------------------------------
// Rows i in [i0, i1), each a (frame, POI) pair: the window's ns pixels (dx[s], dy[s]) about
// the whole-pixel centre (cx[i], cy[i]) mapped into the frame at plane off[i] by the
// quadratic maps pm[i] (12: x = pm[0..5] . (1, dx, dy, dx^2, dx dy, dy^2), y = pm[6..11] .
// the same; centre and shift folded in), sampled there, brought to the reference's grey
// levels over the window (mean and norm matched: the reference's mr[i], sr[i] where the
// whole window is inside both images, else its own pixels ref[...] over the pixels inside)
// and weighted by tent[s] wf[i] (0 outside). Out (N, ns) double: the weighted value a and
// the weight wt; (N,) double rs: the row's noise factor fac[i] (gain lv[i])^2 (a sample's
// share of the frame's noise is wt rs[i], formed where it is added: sts_splat_add). Images
// w x h px (the reference ref (h * w) double).
// The template's samples of one row at a time (sts_splat, sts_splat_fused): the arguments of
// sts_splat, the row's scratch held between rows.
template <typename T>
struct SplatRows {
  const T* flat;
  Geo g;
  int order;
  int64_t ns;
  const double *dx, *dy, *tent, *pm, *cx, *cy;
  const int64_t* off;
  const double *wf, *lv, *fac, *mr, *sr, *ref;
  int64_t w, h;
  std::vector<T> xs, ys, val, fxs, fys;
  std::vector<double> in, dxx, dxy, dyy;
  std::vector<int32_t> idx;

  SplatRows(const T* flat_, Geo g_, int order_, int64_t ns_, const double* dx_,
            const double* dy_, const double* tent_, const double* pm_, const double* cx_,
            const double* cy_, const int64_t* off_, const double* wf_, const double* lv_,
            const double* fac_, const double* mr_, const double* sr_, const double* ref_,
            int64_t w_, int64_t h_)
      : flat(flat_), g(g_), order(order_), ns(ns_), dx(dx_), dy(dy_), tent(tent_), pm(pm_),
        cx(cx_), cy(cy_), off(off_), wf(wf_), lv(lv_), fac(fac_), mr(mr_), sr(sr_),
        ref(ref_), w(w_), h(h_), xs(ns_), ys(ns_), val(ns_), fxs(ns_), fys(ns_), in(ns_),
        dxx(ns_), dxy(ns_), dyy(ns_), idx(ns_) {
    for (int64_t s = 0; s < ns; ++s) {
      dxx[s] = dx[s] * dx[s];
      dxy[s] = dx[s] * dy[s];
      dyy[s] = dy[s] * dy[s];
    }
  }

  // Row i: its weighted values ai[ns] and weights wi[ns]; returns its noise factor.
  double row(int64_t i, double* ai, double* wi) {
    const double wmax = double(w - 1), hmax = double(h - 1);
    const double* q = pm + i * 12;
    // the reference configuration's window is inside where its corners are
    const double ci = cx[i], cj = cy[i];
    const bool ref_in = ci + dx[0] >= 0 && ci + dx[ns - 1] <= wmax && cj + dy[0] >= 0 &&
                        cj + dy[ns - 1] <= hmax;
    double n_in = 0;
    for (int64_t s = 0; s < ns; ++s) {
      const double x = q[0] + q[1] * dx[s] + q[2] * dy[s] + q[3] * dxx[s] + q[4] * dxy[s] +
                       q[5] * dyy[s];
      const double y = q[6] + q[7] * dx[s] + q[8] * dy[s] + q[9] * dxx[s] + q[10] * dxy[s] +
                       q[11] * dyy[s];
      xs[s] = T(x);
      ys[s] = T(y);
      const double rx = ci + dx[s], ry = cj + dy[s];
      const bool ok = (x >= 0) & (x <= wmax) & (y >= 0) & (y <= hmax) & (rx >= 0) &
                      (rx <= wmax) & (ry >= 0) & (ry <= hmax);
      in[s] = ok ? 1.0 : 0.0;
      n_in += in[s];
    }
    const bool whole = ref_in && n_in == double(ns);
    if (order == 3)
      sample_points<T, 3>(flat + off[i], g, T(0), T(0), xs.data(), ys.data(), ns, idx.data(),
                          fxs.data(), fys.data(), val.data());
    else
      sample_points<T, 5>(flat + off[i], g, T(0), T(0), xs.data(), ys.data(), ns, idx.data(),
                          fxs.data(), fys.data(), val.data());
    double sum = 0;
    for (int64_t s = 0; s < ns; ++s) sum += double(val[s]) * in[s];
    if (!std::isfinite(sum)) {  // a frame with NaN or inf pixels: those samples count 0
      for (int64_t s = 0; s < ns; ++s)
        if (!std::isfinite(double(val[s]))) val[s] = T(0);
      sum = 0;
      for (int64_t s = 0; s < ns; ++s) sum += double(val[s]) * in[s];
    }
    const double c = n_in > 0 ? n_in : 1.0;
    const double mf = sum / c;
    double ss = 0;
    for (int64_t s = 0; s < ns; ++s) {
      const double v = (double(val[s]) - mf) * in[s];
      ss += v * v;
    }
    const double sf = std::sqrt(ss);
    double m_r = mr[i], s_r = sr[i];
    if (!whole) {  // the reference's own pixels of the window, over those inside
      const int64_t size = w * h;
      const int64_t base = int64_t(cj) * w + int64_t(ci);
      double rsum = 0;
      for (int64_t s = 0; s < ns; ++s) {
        const int64_t k = std::min(std::max(base + int64_t(dy[s]) * w + int64_t(dx[s]),
                                            int64_t(0)), size - 1);
        rsum += ref[k] * in[s];
      }
      m_r = rsum / c;
      double r2 = 0;
      for (int64_t s = 0; s < ns; ++s) {
        const int64_t k = std::min(std::max(base + int64_t(dy[s]) * w + int64_t(dx[s]),
                                            int64_t(0)), size - 1);
        const double e = (ref[k] - m_r) * in[s];
        r2 += e * e;
      }
      s_r = std::sqrt(r2);
    }
    const double gain = sf > 0 ? s_r / std::max(sf, 1e-12) : 1.0;
    const double wfi = wf[i], off_v = m_r - mf * gain;
    for (int64_t s = 0; s < ns; ++s) {
      const double weight = tent[s] * wfi * in[s];
      ai[s] = (double(val[s]) * gain + off_v) * weight;
      wi[s] = weight;
    }
    return fac[i] * (gain * lv[i]) * (gain * lv[i]);
  }
};

STS_KERNEL(sts_splat, (const T* flat, int64_t wp, double x_lo, double x_hi, double y_lo,
                       double y_hi, int64_t shift, int order, int64_t i0, int64_t i1,
                       int64_t ns, const double* dx, const double* dy, const double* tent,
                       const double* pm, const double* cx, const double* cy,
                       const int64_t* off, const double* wf, const double* lv,
                       const double* fac, const double* mr, const double* sr,
                       const double* ref, int64_t w, int64_t h, double* a, double* wt,
                       double* rs)) {
  if (order != 3 && order != 5) return 1;
  SplatRows<T> rows(flat, Geo{wp, x_lo, x_hi, y_lo, y_hi, shift}, order, ns, dx, dy, tent, pm,
                    cx, cy, off, wf, lv, fac, mr, sr, ref, w, h);
  for (int64_t i = i0; i < i1; ++i) rs[i] = rows.row(i, a + i * ns, wt + i * ns);
  return 0;
}

// One row of the template's samples (values a[ns], weights wt[ns], the row's noise factor
// ri) added at its pixels k[ns] that lie in [lo, hi): sums[k] += a, fw[k] += wt, fn[k] += wt
// ri (the product rounded, then added) (sts_splat_add, sts_splat_fused).
template <typename T>
inline void splat_add_row(const int64_t* k, const T* a, const T* wt, T ri, int64_t ns,
                          int64_t lo, int64_t hi, T* sums, T* fw, T* fn) {
  for (int64_t s = 0; s < ns; ++s) {
    const int64_t j = k[s];
    if (j < lo || j >= hi) continue;
    T share = wt[s] * ri;
#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
    asm volatile("" : "+x"(share));  // rounded here: not fused into the add (-ffp-contract)
#endif
    sums[j] += a[s];
    fw[j] += wt[s];
    fn[j] += share;
  }
}

// Rows i in [i0, i1) of sts_splat's outputs a, wt (N, ns) and rs (N,), each a (frame, POI)
// pair: added to the sums over the n_px pixels the windows cover, k = local[poi[i] * ns + s]
// the pixel of sample s: sums[k] += a, and the row's frame's pf_w[frame[i] * n_px + k] += wt,
// pf_n[...] += wt rs[i] (the product rounded before it is added: the numbers of a product
// stored, then added). Each bin's values added in row order, as index_add_ adds them on the
// CPU (kernels/scatter.py): call it on one thread, over all rows at once.
STS_KERNEL(sts_splat_add, (int64_t i0, int64_t i1, int64_t ns, int64_t n_px, const T* a,
                           const T* wt, const T* rs, const int64_t* poi,
                           const int64_t* frame, const int64_t* local, T* sums, T* pf_w,
                           T* pf_n)) {
  for (int64_t i = i0; i < i1; ++i)
    splat_add_row(local + poi[i] * ns, a + i * ns, wt + i * ns, rs[i], ns, 0, n_px, sums,
                  pf_w + frame[i] * n_px, pf_n + frame[i] * n_px);
  return 0;
}

// Pixels p in [i0, i1) of the n_px covered ones: every row r in [0, n) (a (frame, POI)
// pair, as in sts_splat) whose window reaches them (its pixels local[poi[r] * ns + s],
// ascending in s) sampled as sts_splat samples it and added to those pixels as sts_splat_add
// adds it: each pixel's sums are those of sts_splat then sts_splat_add to the bit (rows in
// order), whatever the split of the pixels, with no (N, ns) arrays between (a row whose
// window straddles two splits is sampled by both).
STS_KERNEL(sts_splat_fused, (const T* flat, int64_t wp, double x_lo, double x_hi,
                             double y_lo, double y_hi, int64_t shift, int order, int64_t i0,
                             int64_t i1, int64_t n, int64_t ns, const double* dx,
                             const double* dy, const double* tent, const double* pm,
                             const double* cx, const double* cy, const int64_t* off,
                             const double* wf, const double* lv, const double* fac,
                             const double* mr, const double* sr, const double* ref,
                             int64_t w, int64_t h, const int64_t* poi, const int64_t* frame,
                             const int64_t* local, int64_t n_px, double* sums, double* pf_w,
                             double* pf_n)) {
  if (order != 3 && order != 5) return 1;
  SplatRows<T> rows(flat, Geo{wp, x_lo, x_hi, y_lo, y_hi, shift}, order, ns, dx, dy, tent, pm,
                    cx, cy, off, wf, lv, fac, mr, sr, ref, w, h);
  std::vector<double> a(ns), wt(ns);
  for (int64_t r = 0; r < n; ++r) {
    const int64_t* k = local + poi[r] * ns;
    if (k[ns - 1] < i0 || k[0] >= i1) continue;
    const double ri = rows.row(r, a.data(), wt.data());
    splat_add_row(k, a.data(), wt.data(), ri, ns, i0, i1, sums, pf_w + frame[r] * n_px,
                  pf_n + frame[r] * n_px);
  }
  return 0;
}

// Pixels p in [i0, i1) of one frame's sums over the n_px covered pixels (sts_splat_add's
// pf_w, pf_n) folded into the template's: sums_w[p] += pf_w[p], sums_n[p] += pf_n[p] / wf *
// pf_w[p] (the frame's share of the noise; each operation rounded on its own, as torch's
// div_, mul_ and add_ round them), then pf_w[p], pf_n[p] cleared for the next frame. One pass
// instead of five over the pixels; any split over threads gives the same numbers.
STS_KERNEL(sts_splat_finish, (int64_t i0, int64_t i1, double wf, T* pf_w, T* pf_n, T* sums_w,
                              T* sums_n)) {
  const T f = T(wf);
  for (int64_t p = i0; p < i1; ++p) {
    const T w = pf_w[p];
    T share = pf_n[p] / f;
    share = share * w;
#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
    asm volatile("" : "+x"(share));  // rounded here: not fused into the add (-ffp-contract)
#endif
    sums_w[p] += w;
    sums_n[p] += share;
    pf_w[p] = T(0);
    pf_n[p] = T(0);
  }
  return 0;
}

}  // namespace

// ---- the library's interface: the ABI version and the kernel declarations ------------------
extern "C" {

// Version of this interface (the sts_kernel_* functions and what the kernels' parameters
// mean); native/declarations.py refuses a library of another version.
int sts_abi_version() { return 18; }

int sts_kernel_count() { return int(declarations().size()); }

// Kernel i's name (without the _f32/_f64 suffix), null past the end.
const char* sts_kernel_name(int i) {
  return i >= 0 && i < sts_kernel_count() ? declarations()[i].name : nullptr;
}

// Kernel i's parameter list as written, e.g. "(const T* flat, int64_t wp, ...)".
const char* sts_kernel_params(int i) {
  return i >= 0 && i < sts_kernel_count() ? declarations()[i].params : nullptr;
}

// Kinds of the parameters of kernel i's float (f64 = 0) or double (f64 = 1) instance, as
// compiled: e.g. "*f32,i64,f64,...".
const char* sts_kernel_kinds(int i, int f64) {
  return i >= 0 && i < sts_kernel_count() ? declarations()[i].kinds[f64 ? 1 : 0].c_str()
                                          : nullptr;
}

// Address of that instance (an int function of those parameters, C calling convention).
void* sts_kernel_address(int i, int f64) {
  return i >= 0 && i < sts_kernel_count() ? declarations()[i].address[f64 ? 1 : 0] : nullptr;
}

}  // extern "C"
