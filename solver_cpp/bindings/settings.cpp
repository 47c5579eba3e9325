#include "bindings.hpp"
#include "rd3g/problem.hpp"

using namespace rd3g;

void bind_settings(py::module_& m) {
  py::enum_<LinearSolver>(m, "LinearSolver")
      .value("riccati", LinearSolver::Riccati)
      .value("sparse_lu", LinearSolver::SparseLU)
      .value("lscg", LinearSolver::LSCG)
      .value("sparse_qr", LinearSolver::SparseQR);
  py::enum_<BarrierMode>(m, "BarrierMode")
      .value("primal", BarrierMode::Primal)
      .value("primal_dual", BarrierMode::PrimalDual);
  py::class_<Settings> s(m, "Settings");
  s.def(py::init<>());
#define RW(f) s.def_readwrite(#f, &Settings::f)
  RW(tol); RW(max_iter); RW(time_limit); RW(rho_init); RW(rho_floor_factor); RW(rho_kappa); RW(rho_beta); RW(rho_progress); RW(ls_alpha); RW(ls_beta);
  RW(ls_max_steps); RW(violation_tol); RW(dynamics_tol); RW(multiplier_tol); RW(barrier_margin); RW(lm_tries); RW(lm_below_step); RW(lm_nu_init);
  RW(linear_solver); RW(refinement_steps); RW(barrier); RW(fraction_to_boundary); RW(domain_fraction); RW(lscg_tol); RW(lscg_max_iter); RW(restarts); RW(stall_window); RW(stall_floor_window); RW(crawl_window); RW(crawl_ratio); RW(polish_gap); RW(restart_u_std); RW(second_order_gap); RW(second_order_tol); RW(restart_on_saddle); RW(saddle_escapes); RW(saddle_step); RW(saddle_rho); RW(saddle_inertia); RW(saddle_inertia_restarts); RW(violation_memory); RW(rho_on_stall); RW(restart_rho_progress); RW(restart_violation_memory); RW(restart_rho_on_stall); RW(deep_overlap); RW(best_response_rounds); RW(best_response_attempt); RW(best_response_max_iter); RW(best_response_margin); RW(verbose);
#undef RW
}
