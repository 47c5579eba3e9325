#include "bindings.hpp"
#include "rd3g/problem.hpp"

using namespace rd3g;

void bind_settings(py::module_& m) {
  py::enum_<LinearSolver>(m, "LinearSolver")
      .value("sparse_lu", LinearSolver::SparseLU)
      .value("lscg", LinearSolver::LSCG)
      .value("sparse_qr", LinearSolver::SparseQR);
  py::class_<Settings> s(m, "Settings");
  s.def(py::init<>());
#define RW(f) s.def_readwrite(#f, &Settings::f)
  RW(tol); RW(max_iter); RW(time_limit); RW(rho_init); RW(rho_kappa); RW(rho_beta); RW(ls_alpha); RW(ls_beta);
  RW(ls_max_steps); RW(violation_tol); RW(multiplier_tol); RW(barrier_margin); RW(regularization);
  RW(linear_solver); RW(lscg_tol); RW(lscg_max_iter); RW(verbose);
#undef RW
}
