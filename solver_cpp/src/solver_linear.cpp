// The Newton step's linear solve: Riccati, sparse LU, LSCG or SparseQR, their fallbacks (the regularised
// least-squares step after LU, SparseQR after LSCG), and the Levenberg-Marquardt direction.
#include "rd3g/solver.hpp"

#include <Eigen/IterativeLinearSolvers>
#include <Eigen/SparseCholesky>
#include <algorithm>
#include <cmath>
#include <cstdio>

#include "rd3g/clock.hpp"

namespace rd3g {

namespace {
constexpr int kRefinementSteps = 2;  // iterative refinement steps after each sparse LU solve
// LSCG iterations between deadline checks when a time limit is set.
constexpr int kLscgChunk = 50;
// Sparse factorisation speed assumed before this solver has measured its own (flop/s): low, so that a
// prediction errs towards not starting a factorisation that might overrun the time limit.
constexpr double kDefaultFlopRate = 2e8;

// Sparse LDLT that reports the flops of its numeric factorisation once its pattern is analysed, so the
// cost of a factorisation is known before it starts (sum over columns of c^2 + c, c = entries below
// the diagonal of L; the counts are Eigen's own, kept in a protected member after analyzePattern).
class CountedLDLT : public Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>, Eigen::Lower> {
 public:
  double factor_flops() const {
    double f = 0;
    for (Eigen::Index j = 0; j < this->m_nonZerosPerCol.size(); ++j) {
      const double c = this->m_nonZerosPerCol[j];
      f += c * c + c;
    }
    return f;
  }
};
}  // namespace

void Solver::build_J() {
  if (J_built_) return;
  J_.resize(n_vars_, n_vars_);
  J_.setFromTriplets(trip_.begin(), trip_.end());
  J_.makeCompressed();
  J_built_ = true;
}

bool Solver::solve_linear(Vec& dy, Info& info) {
  J_built_ = false;
  lm_ready_ = false;
  if (settings_.linear.solver == LinearSolver::Riccati && solve_riccati(dy, info)) return true;
  build_J();
  neg_rhs_.head(n_vars_) = -rhs_.head(n_vars_);
  switch (settings_.linear.solver) {
    case LinearSolver::Riccati:
    case LinearSolver::SparseLU:
      return solve_lu(dy, info) || solve_least_squares(dy, info);
    case LinearSolver::LSCG: {
      bool failed = false;
      if (solve_lscg(dy, failed)) return true;
      return !failed && solve_qr(dy, info);
    }
    case LinearSolver::SparseQR: {
      const int fallbacks = info.qr_fallbacks;
      const bool ok = solve_qr(dy, info);
      info.qr_fallbacks = fallbacks;  // not a fallback when QR is the chosen method
      return ok;
    }
  }
  return false;
}

bool Solver::solve_riccati(Vec& dy, Info& info) {
  const int n = n_vars_;
  if (!riccati_.solve(trip_, n, rhs_, dy)) return false;
  // Check the step against the assembled system (O(nnz)); a poorly conditioned recursion falls back to LU.
  lin_res_.head(n) = rhs_.head(n);
  for (const auto& t : trip_) lin_res_[t.row()] += t.value() * dy[t.col()];
  if (lin_res_.head(n).norm() <= 1e-9 * std::max(1.0, rhs_.head(n).norm())) {
    info.riccati_solves++;
    return true;
  }
  if (settings_.verbose) std::printf("   Riccati residual %.2e: falling back to sparse LU\n", lin_res_.head(n).norm());
  return false;
}

bool Solver::solve_lu(Vec& dy, Info& info) {
  const int n = n_vars_;
  const auto rhs = neg_rhs_.head(n);
  // The sparsity pattern depends only on which constraints are equalities: analyse it only when that changes.
  if (!lu_analyzed_ || pattern_state_ != state_) {
    lu_.analyzePattern(J_);
    pattern_state_ = state_;
    lu_analyzed_ = true;
    info.symbolic_factorizations++;
  }
  lu_.factorize(J_);
  if (lu_.info() == Eigen::Success) {
    dy.head(n) = lu_.solve(rhs);
    // Iterative refinement with the same factors: the Newton matrix can be badly scaled (barrier
    // curvature z/(-h) next to O(1) entries), and an inaccurate step is not a descent direction.
    for (int ref = 0; ref < kRefinementSteps; ++ref) {
      lin_res_.head(n) = rhs - J_ * dy.head(n);
      const double res_norm = lin_res_.head(n).norm();
      if (settings_.verbose) std::printf("   linear residual %.2e (rhs %.2e)\n", res_norm, rhs.norm());
      if (res_norm <= 1e-12 * rhs.norm()) break;
      dy.head(n) += lu_.solve(lin_res_.head(n));
    }
    if (lu_.info() == Eigen::Success && dy.head(n).allFinite()) return true;
  }
  lu_analyzed_ = false;  // a failed factorisation may leave the symbolic data unusable
  return false;
}

bool Solver::solve_lscg(Vec& dy, bool& timed_out) {
  const int n = n_vars_;
  const auto rhs = neg_rhs_.head(n);
  Eigen::LeastSquaresConjugateGradient<SpMat> cg;
  cg.setTolerance(settings_.linear.lscg_tol);
  cg.compute(J_);
  if (settings_.time_limit <= 0) {
    cg.setMaxIterations(settings_.linear.lscg_max_iter);
    dy.head(n) = cg.solve(rhs);
  } else {
    // In chunks, so that the deadline is checked inside a long solve (each chunk restarts from the last
    // iterate, which changes the iterates slightly compared with one run).
    dy.head(n).setZero();
    for (int done = 0; done < settings_.linear.lscg_max_iter; done += kLscgChunk) {
      cg.setMaxIterations(std::min(kLscgChunk, settings_.linear.lscg_max_iter - done));
      dy.head(n) = cg.solveWithGuess(rhs, dy.head(n));
      if (cg.info() == Eigen::Success) break;
      if (past_deadline()) {
        timed_out_ = timed_out = true;
        return false;
      }
    }
  }
  return cg.info() == Eigen::Success && dy.head(n).allFinite();
}

// A singular Newton matrix (LU failed): the regularised least-squares step, with or without a time limit, so
// that a limit the solve does not reach leaves its path unchanged; its cost, unlike SparseQR's, is known
// before it starts.
bool Solver::solve_least_squares(Vec& dy, Info& info) {
  if (past_deadline()) {
    timed_out_ = true;
    return false;
  }
  if (!bounded_least_squares(dy)) return false;
  info.qr_fallbacks++;
  return true;
}

// SparseQR cannot be interrupted: with a time limit it is started only when this solver's last QR
// fits into the time left; otherwise the bounded least-squares fallback takes its place.
bool Solver::solve_qr(Vec& dy, Info& info) {
  const int n = n_vars_;
  if (past_deadline()) {
    timed_out_ = true;
    return false;
  }
  if (settings_.time_limit > 0 && qr_would_overrun()) {
    if (settings_.verbose) std::printf("   SparseQR would overrun the time limit: regularised least squares\n");
    if (solve_least_squares(dy, info)) return true;
    timed_out_ = true;
    return false;
  }
  const auto t_qr = Clock::now();
  Eigen::SparseQR<SpMat, Eigen::COLAMDOrdering<int>> qr;
  qr.compute(J_);
  last_qr_seconds_ = seconds_since(t_qr);
  if (settings_.verbose) std::printf("   SparseQR took %.3g s\n", last_qr_seconds_);
  if (qr.info() != Eigen::Success) return false;
  dy.head(n) = qr.solve(neg_rhs_.head(n));
  info.qr_fallbacks++;
  return qr.info() == Eigen::Success && dy.head(n).allFinite();
}

bool Solver::past_deadline() const {
  return settings_.time_limit > 0 && seconds_since(t_start_) > settings_.time_limit;
}

bool Solver::next_iteration_overruns() {
  // An iteration (assembly, linear solve, line search) cannot be cut short: with a time limit the next one
  // is not started when the last one, measured between these checks, would not fit into the time left.
  if (settings_.time_limit <= 0) return false;
  const auto now = Clock::now();
  if (have_iteration_start_) last_iteration_seconds_ = std::chrono::duration<double>(now - iteration_start_).count();
  iteration_start_ = now;
  have_iteration_start_ = true;
  return past_deadline() || last_iteration_seconds_ > time_left();
}

double Solver::time_left() const { return settings_.time_limit - seconds_since(t_start_); }

double Solver::flop_rate() const { return ldlt_flop_rate_ > 0 ? ldlt_flop_rate_ : kDefaultFlopRate; }

double Solver::normal_matrix_flops() const {
  // Forming J'J costs the sum over rows of (entries in the row)^2.
  row_count_.setZero(n_vars_);
  for (Eigen::Index k = 0; k < J_.outerSize(); ++k)
    for (SpMat::InnerIterator it(J_, k); it; ++it) row_count_[it.row()] += 1;
  return row_count_.squaredNorm();
}

bool Solver::qr_would_overrun() const {
  // SparseQR's duration cannot be predicted from the pattern: its Householder vectors fill in from about 80x
  // (10-car merge) to 1800x (a 4-agent fuzz problem) the flops of an LDLT of J'J. Under a time limit it is
  // started only when this solver's own last QR fits; otherwise the bounded least-squares step replaces it.
  return last_qr_seconds_ <= 0 || last_qr_seconds_ > time_left();
}

bool Solver::bounded_least_squares(Vec& dy) {
  // Tikhonov-regularised normal equations (J'J + delta I) dy = J'(-rhs) by sparse LDLT: the least-squares
  // step SparseQR would give (up to delta), at a cost known before the numeric factorisation starts, which
  // is skipped when it would not fit into the time left (timed_out_ is then set). Two refinement steps remove
  // most of delta's bias.
  const int n = n_vars_;
  const bool timed = settings_.time_limit > 0;
  if (timed && normal_matrix_flops() / flop_rate() > time_left()) {
    timed_out_ = true;
    return false;
  }
  SpMat JtJ = J_.transpose() * J_;
  const double dmax = JtJ.diagonal().cwiseAbs().maxCoeff();
  SpMat eye(n, n);
  eye.setIdentity();
  const double delta = 1e-10 * (dmax > 0 ? dmax : 1.0);
  SpMat M = JtJ + delta * eye;
  CountedLDLT ldlt;
  ldlt.analyzePattern(M);
  const double flops = ldlt.factor_flops();
  if (timed && flops / flop_rate() > time_left()) {
    timed_out_ = true;
    return false;
  }
  const auto t0 = Clock::now();
  ldlt.factorize(M);
  const double sec = seconds_since(t0);
  if (settings_.verbose)
    std::printf("   regularised LDLT: %.3g flop predicted %.3g s, took %.3g s\n", flops, flops / flop_rate(), sec);
  if (sec > 1e-3) ldlt_flop_rate_ = flops / sec;  // too short a factorisation measures the overhead, not the rate
  if (ldlt.info() != Eigen::Success) return false;
  const Vec g = J_.transpose() * neg_rhs_.head(n);
  Vec x = ldlt.solve(g);
  for (int r = 0; r < 2 && x.allFinite(); ++r) x += ldlt.solve(g - JtJ * x);
  if (!x.allFinite()) return false;
  dy.head(n) = x;
  return true;
}

// Levenberg-Marquardt direction on ||r||^2: (J'J + nu I) dy = -J' r, always a descent direction.
// The tries of one iteration (several nu) reuse J'J, J'r and the symbolic analysis: they were most of the
// line-search time on dense games (up to 4 full LDLTs per iteration).
bool Solver::solve_levenberg_marquardt(double nu, Vec& dy) {
  if (!lm_ready_) {
    build_J();
    const bool same_pattern = lm_normal_.compute(J_, lm_JtJ_);
    if (!lm_analyzed_ || (!same_pattern && !lm_ldlt_.same_pattern(lm_JtJ_))) {
      lm_analyzed_ = false;
      if (!lm_ldlt_.analyze(lm_JtJ_)) return false;
      lm_analyzed_ = true;
    }
    lm_ldlt_.load(lm_JtJ_);
    lm_Jtr_ = J_.transpose() * rhs_.head(n_vars_);
    lm_ready_ = true;
  }
  if (!lm_ldlt_.factorize_shifted(nu)) return false;
  lm_ldlt_.solve(lm_Jtr_, dy.head(n_vars_));
  dy.head(n_vars_) = -dy.head(n_vars_);
  if (settings_.verbose) std::printf("   Levenberg-Marquardt step, nu %.2e\n", nu);
  return dy.head(n_vars_).allFinite();
}

}  // namespace rd3g
