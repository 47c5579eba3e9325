// Structured solve of RD3G's Newton system when it has no equality-constraint rows: with the variables
// ordered stage by stage, the system is block-tridiagonal in time, and a backward recursion on
// lambda_k = P_{k+1} dx_{k+1} + p_{k+1} (the coupled, nonsymmetric Riccati recursion of an open-loop
// game) solves it in O(T (N nx)^3) instead of a general sparse LU.
#pragma once
#include <Eigen/Dense>
#include <Eigen/Sparse>
#include <vector>

namespace rd3g {

class StageRiccati {
 public:
  /// N agents, horizon T, sizes nx, nu; variables per stage and agent ordered [u, lambda, x_{k+1}].
  void setup(int N, int T, int nx, int nu);
  /// Solves J dy = -rhs from J's triplets (primal variables only). Returns false when the triplets do
  /// not have the stage structure or a stage matrix is singular; the caller then uses a general solver.
  bool solve(const std::vector<Eigen::Triplet<double>>& trip, const Eigen::VectorXd& rhs, Eigen::VectorXd& dy);

 private:
  int N_ = 0, T_ = 0, nx_ = 0, nu_ = 0, X_ = 0, U_ = 0;
  // Per stage k = 0..T-1 (x-row blocks Q* belong to time k+1 and are stored at index k):
  std::vector<Eigen::MatrixXd> Ruu_, Rux_, Rul_, Fx_, Fu_, Qxx_, Qxu_, Qxl_, P_, K_;
  std::vector<Eigen::VectorXd> p_, kap_;
};

}  // namespace rd3g
