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
#define RW(T, f) .def_readwrite(#f, &T::f)
  py::class_<BarrierSettings>(m, "BarrierSettings").def(py::init<>())
      RW(BarrierSettings, mode) RW(BarrierSettings, rho_init) RW(BarrierSettings, rho_floor_factor)
      RW(BarrierSettings, rho_kappa) RW(BarrierSettings, rho_beta) RW(BarrierSettings, rho_progress) RW(BarrierSettings, rho_after_step)
      RW(BarrierSettings, margin);
  py::class_<LineSearchSettings>(m, "LineSearchSettings").def(py::init<>())
      RW(LineSearchSettings, alpha) RW(LineSearchSettings, beta) RW(LineSearchSettings, max_steps)
      RW(LineSearchSettings, violation_memory) RW(LineSearchSettings, lm_tries) RW(LineSearchSettings, to_crossing);
  py::class_<LinearSettings>(m, "LinearSettings").def(py::init<>())
      RW(LinearSettings, solver) RW(LinearSettings, lscg_tol)
      RW(LinearSettings, lscg_max_iter);
  py::class_<StallSettings>(m, "StallSettings").def(py::init<>())
      RW(StallSettings, window) RW(StallSettings, floor_window) RW(StallSettings, crawl_window)
      RW(StallSettings, crawl_ratio) RW(StallSettings, polish_gap);
  py::class_<RestartSettings>(m, "RestartSettings").def(py::init<>())
      RW(RestartSettings, count) RW(RestartSettings, rho_progress)
      RW(RestartSettings, violation_memory) RW(RestartSettings, rho_on_stall) RW(RestartSettings, deep_overlap);
  py::class_<BestResponseSettings>(m, "BestResponseSettings").def(py::init<>())
      RW(BestResponseSettings, rounds) RW(BestResponseSettings, max_iter)
      RW(BestResponseSettings, margin) RW(BestResponseSettings, restarts);
  py::class_<SecondOrderSettings>(m, "SecondOrderSettings").def(py::init<>())
      RW(SecondOrderSettings, gap) RW(SecondOrderSettings, tol) RW(SecondOrderSettings, restart_on_saddle)
      RW(SecondOrderSettings, escapes)
      RW(SecondOrderSettings, inertia);
  py::class_<PassingOrderSettings>(m, "PassingOrderSettings").def(py::init<>())
      RW(PassingOrderSettings, candidates) RW(PassingOrderSettings, polish) RW(PassingOrderSettings, polish_iter)
      RW(PassingOrderSettings, max_iter) RW(PassingOrderSettings, offset) RW(PassingOrderSettings, before_newton);
  // Groups are returned by reference (settings.stall.window = 8 changes the settings).
  py::class_<Settings>(m, "Settings").def(py::init<>())
      RW(Settings, tol) RW(Settings, max_iter) RW(Settings, time_limit) RW(Settings, violation_tol)
      RW(Settings, dynamics_tol) RW(Settings, stationarity_tol) RW(Settings, domain_fraction) RW(Settings, verbose)
      RW(Settings, barrier) RW(Settings, line_search) RW(Settings, linear) RW(Settings, stall) RW(Settings, restart)
      RW(Settings, best_response) RW(Settings, second_order) RW(Settings, order);
#undef RW
}
