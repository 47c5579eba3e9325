// Forward-mode dual numbers with respect to K inputs: Jet2 carries value, gradient and Hessian, Jet1 value and
// gradient only. Used to give models exact (not finite-difference) derivatives where deriving them by hand would
// be error-prone; the finite-difference test in tests/test_derivatives.py checks them. Jet1 computes its value
// and gradient with the same operations as Jet2 (the gradient never reads the Hessian), so a model evaluated
// with Jet1 where no Hessian is needed (the line search's residuals) gives bit-identical values and Jacobians
// at a fraction of the cost.
#pragma once
#include <Eigen/Dense>
#include <cmath>

namespace rd3g {

template <int K>
struct Jet2 {
  using G = Eigen::Matrix<double, K, 1>;
  using H = Eigen::Matrix<double, K, K>;
  double v = 0.0;
  G g = G::Zero();
  H h = H::Zero();

  static Jet2 constant(double c) { Jet2 r; r.v = c; return r; }
  static Jet2 variable(double c, int i) { Jet2 r; r.v = c; r.g[i] = 1.0; return r; }
};

// Chain rule for a scalar function with value f0, first derivative f1, second derivative f2.
template <int K>
inline Jet2<K> apply(const Jet2<K>& a, double f0, double f1, double f2) {
  Jet2<K> r;
  r.v = f0;
  r.g = f1 * a.g;
  r.h = f1 * a.h + f2 * (a.g * a.g.transpose());
  return r;
}

template <int K> inline Jet2<K> operator+(const Jet2<K>& a, const Jet2<K>& b) { Jet2<K> r; r.v = a.v + b.v; r.g = a.g + b.g; r.h = a.h + b.h; return r; }
template <int K> inline Jet2<K> operator-(const Jet2<K>& a, const Jet2<K>& b) { Jet2<K> r; r.v = a.v - b.v; r.g = a.g - b.g; r.h = a.h - b.h; return r; }
template <int K> inline Jet2<K> operator+(const Jet2<K>& a, double c) { Jet2<K> r = a; r.v += c; return r; }
template <int K> inline Jet2<K> operator+(double c, const Jet2<K>& a) { return a + c; }
template <int K> inline Jet2<K> operator-(const Jet2<K>& a, double c) { Jet2<K> r = a; r.v -= c; return r; }
template <int K> inline Jet2<K> operator-(double c, const Jet2<K>& a) { Jet2<K> r; r.v = c - a.v; r.g = -a.g; r.h = -a.h; return r; }
template <int K> inline Jet2<K> operator*(double c, const Jet2<K>& a) { Jet2<K> r; r.v = c * a.v; r.g = c * a.g; r.h = c * a.h; return r; }
template <int K> inline Jet2<K> operator*(const Jet2<K>& a, double c) { return c * a; }
template <int K>
inline Jet2<K> operator*(const Jet2<K>& a, const Jet2<K>& b) {
  Jet2<K> r;
  r.v = a.v * b.v;
  r.g = a.v * b.g + b.v * a.g;
  r.h = a.v * b.h + b.v * a.h + a.g * b.g.transpose() + b.g * a.g.transpose();
  return r;
}

// ---------------------------------------------------------------------------------------------
template <int K>
struct Jet1 {
  using G = Eigen::Matrix<double, K, 1>;
  double v = 0.0;
  G g = G::Zero();

  static Jet1 constant(double c) { Jet1 r; r.v = c; return r; }
  static Jet1 variable(double c, int i) { Jet1 r; r.v = c; r.g[i] = 1.0; return r; }
};

// As apply() for Jet2; the second derivative f2 is not needed.
template <int K>
inline Jet1<K> apply(const Jet1<K>& a, double f0, double f1, double /*f2*/) {
  Jet1<K> r;
  r.v = f0;
  r.g = f1 * a.g;
  return r;
}

template <int K> inline Jet1<K> operator+(const Jet1<K>& a, const Jet1<K>& b) { Jet1<K> r; r.v = a.v + b.v; r.g = a.g + b.g; return r; }
template <int K> inline Jet1<K> operator-(const Jet1<K>& a, const Jet1<K>& b) { Jet1<K> r; r.v = a.v - b.v; r.g = a.g - b.g; return r; }
template <int K> inline Jet1<K> operator+(const Jet1<K>& a, double c) { Jet1<K> r = a; r.v += c; return r; }
template <int K> inline Jet1<K> operator+(double c, const Jet1<K>& a) { return a + c; }
template <int K> inline Jet1<K> operator-(const Jet1<K>& a, double c) { Jet1<K> r = a; r.v -= c; return r; }
template <int K> inline Jet1<K> operator-(double c, const Jet1<K>& a) { Jet1<K> r; r.v = c - a.v; r.g = -a.g; return r; }
template <int K> inline Jet1<K> operator*(double c, const Jet1<K>& a) { Jet1<K> r; r.v = c * a.v; r.g = c * a.g; return r; }
template <int K> inline Jet1<K> operator*(const Jet1<K>& a, double c) { return c * a; }
template <int K>
inline Jet1<K> operator*(const Jet1<K>& a, const Jet1<K>& b) {
  Jet1<K> r;
  r.v = a.v * b.v;
  r.g = a.v * b.g + b.v * a.g;
  return r;
}

// Elementary functions of either jet, written once through its apply().
template <template <int> class Jet, int K> inline Jet<K> inv(const Jet<K>& a) { const double i = 1.0 / a.v; return apply(a, i, -i * i, 2.0 * i * i * i); }
template <template <int> class Jet, int K> inline Jet<K> operator/(const Jet<K>& a, const Jet<K>& b) { return a * inv(b); }
template <template <int> class Jet, int K> inline Jet<K> sin(const Jet<K>& a) { return apply(a, std::sin(a.v), std::cos(a.v), -std::sin(a.v)); }
template <template <int> class Jet, int K> inline Jet<K> cos(const Jet<K>& a) { return apply(a, std::cos(a.v), -std::sin(a.v), -std::cos(a.v)); }
template <template <int> class Jet, int K>
inline Jet<K> tan(const Jet<K>& a) {
  const double t = std::tan(a.v), s = 1.0 + t * t;
  return apply(a, t, s, 2.0 * t * s);
}
template <template <int> class Jet, int K>
inline Jet<K> atan(const Jet<K>& a) {
  const double d = 1.0 + a.v * a.v;
  return apply(a, std::atan(a.v), 1.0 / d, -2.0 * a.v / (d * d));
}

}  // namespace rd3g
