#include <pybind11/eigen.h>
#include <Eigen/SparseCholesky>
#include <pybind11/stl.h>

#include "bindings.hpp"
#include "rd3g/second_order.hpp"
#include "rd3g/shifted_ldlt.hpp"
#include "rd3g/solver.hpp"
#include "rd3g/validate.hpp"

using namespace rd3g;

void bind_solver(py::module_& m) {
  py::enum_<Status>(m, "Status")
      .value("converged", Status::Converged)
      .value("max_iterations", Status::MaxIterations)
      .value("line_search_failed", Status::LineSearchFailed)
      .value("numerical_error", Status::NumericalError)
      .value("time_limit", Status::TimeLimit)
      .value("stalled", Status::Stalled)
      .value("saddle", Status::Saddle)
      .value("domain_edge", Status::DomainEdge);
  m.def("status_name", &status_name);
  m.def("validate_problem", &validate_problem, py::arg("problem"),
        "Checks every field of a problem (the validation Solver.setup and the baselines run); ValueError names the field.");
  m.def("validate_settings", &validate_settings, py::arg("settings"));
  m.def(
      "tridiagonal_extreme_eigenvalues",
      [](const Vec& d, const Vec& e) {
        // For tests: the second-order test's smallest and largest eigenvalue of a symmetric tridiagonal matrix.
        if (d.size() < 1 || e.size() != d.size() - 1)
          throw std::invalid_argument("d must have length n >= 1 and e length n - 1");
        double lo, hi;
        tridiagonal_extreme_eigenvalues(d, e, lo, hi);
        return std::make_pair(lo, hi);
      },
      py::arg("d"), py::arg("e"));
  m.def(
      "debug_shifted_ldlt",
      [](const std::vector<Eigen::SparseMatrix<double>>& mats, const std::vector<double>& shifts, const Vec& b) {
        // For tests: the Levenberg-Marquardt factorisation (analysed on mats[0], reused for the others, which must
        // share its pattern) solving (A + shift I) x = b for every A and shift, and Eigen's SimplicialLDLT
        // computed afresh on the explicitly shifted matrix, in the same order; and the number of supernodes.
        using SpMat = Eigen::SparseMatrix<double>;
        if (mats.empty()) throw std::invalid_argument("mats must not be empty");
        std::vector<Vec> ours, eigen;
        ShiftedLDLT ldlt;
        SpMat a0 = mats[0];
        a0.makeCompressed();
        if (!ldlt.analyze(a0)) throw std::runtime_error("analysis failed");
        for (const SpMat& m : mats) {
          SpMat a = m;
          a.makeCompressed();
          if (!ldlt.same_pattern(a)) throw std::invalid_argument("every matrix must have mats[0]'s pattern");
          ldlt.load(a);
          for (double s : shifts) {
            Vec x(b.size());
            if (ldlt.factorize_shifted(s)) ldlt.solve(b, x);
            else x.resize(0);
            ours.push_back(x);
            SpMat shifted = a;
            for (int d = 0; d < a.rows(); ++d) shifted.coeffRef(d, d) += s;
            Eigen::SimplicialLDLT<SpMat> ref(shifted);
            eigen.push_back(ref.info() == Eigen::Success ? Vec(ref.solve(b)) : Vec());
          }
        }
        return py::make_tuple(ours, eigen, ldlt.supernodes());
      },
      py::arg("mats"), py::arg("shifts"), py::arg("b"));
  m.def(
      "debug_normal_matrix",
      [](const std::vector<Eigen::SparseMatrix<double>>& js) {
        // For tests: J'J by the Levenberg-Marquardt path's NormalMatrix for each J in turn (planned on the first of
        // a pattern, reused while the pattern holds) and by Eigen's product afresh; whether each reused the plan.
        using SpMat = Eigen::SparseMatrix<double>;
        NormalMatrix nm;
        SpMat a;
        std::vector<SpMat> ours, eigen;
        std::vector<bool> reused;
        for (SpMat j : js) {
          j.makeCompressed();
          reused.push_back(nm.compute(j, a));
          ours.push_back(SpMat(a.triangularView<Eigen::Lower>()));
          SpMat ref = j.transpose() * j;
          eigen.push_back(SpMat(ref.triangularView<Eigen::Lower>()));
        }
        return py::make_tuple(ours, eigen, reused);
      },
      py::arg("js"));
  py::class_<Timings>(m, "Timings")
      .def_readonly("total", &Timings::total)
      .def_readonly("assembly", &Timings::assembly)
      .def_readonly("linear_solve", &Timings::linear_solve)
      .def_readonly("line_search", &Timings::line_search)
      .def_readonly("setup", &Timings::setup)
      .def_readonly("update", &Timings::update);
  py::class_<PassingPair>(m, "PassingPair")
      .def_readonly("i", &PassingPair::i)
      .def_readonly("j", &PassingPair::j)
      .def_readonly("winding", &PassingPair::winding)
      .def_readonly("first", &PassingPair::first)
      .def_readonly("side", &PassingPair::side)
      .def_readonly("gap", &PassingPair::gap);
  py::class_<OrderCandidate>(m, "OrderCandidate")
      .def_readonly("requested", &OrderCandidate::requested)
      .def_readonly("found", &OrderCandidate::found)
      .def_readonly("guess_residual", &OrderCandidate::guess_residual)
      .def_readonly("polished", &OrderCandidate::polished)
      .def_readonly("status", &OrderCandidate::status)
      .def_readonly("iterations", &OrderCandidate::iterations)
      .def_readonly("equilibrium", &OrderCandidate::equilibrium)
      .def_readonly("returned", &OrderCandidate::returned)
      .def_readonly("u", &OrderCandidate::u);
  py::class_<Info>(m, "Info")
      .def_readonly("status", &Info::status)
      .def_readonly("iterations", &Info::iterations)
      .def_readonly("residual_norm", &Info::residual_norm)
      .def_readonly("max_violation", &Info::max_violation)
      .def_readonly("rho", &Info::rho)
      .def_readonly("active_constraints", &Info::active_constraints)
      .def_readonly("symbolic_factorizations", &Info::symbolic_factorizations)
      .def_readonly("qr_fallbacks", &Info::qr_fallbacks)
      .def_readonly("riccati_solves", &Info::riccati_solves)
      .def_readonly("lm_steps", &Info::lm_steps)
      .def_readonly("attempts", &Info::attempts)
      .def_readonly("saddle_escapes", &Info::saddle_escapes)
      .def_readonly("best_response_attempts", &Info::best_response_attempts)
      .def_readonly("best_response_iterations", &Info::best_response_iterations)
      .def_readonly("setups", &Info::setups)
      .def_readonly("passing_order", &Info::passing_order)
      .def_readonly("orders", &Info::orders)
      .def_readonly("order_attempts", &Info::order_attempts)
      .def_readonly("order_iterations", &Info::order_iterations)
      .def_readonly("domain_iterations", &Info::domain_iterations)
      .def_readonly("bounded_start_iterations", &Info::bounded_start_iterations)
      .def_readonly("second_order", &Info::second_order)
      .def_readonly("residual_history", &Info::residual_history)
      .def_readonly("step_history", &Info::step_history)
      .def_readonly("timings", &Info::timings);
  py::class_<WarmStart>(m, "WarmStart")
      .def(py::init<>())
      .def_readwrite("u", &WarmStart::u)
      .def_readwrite("lam", &WarmStart::lambda)
      .def_readwrite("mu", &WarmStart::mu);
  py::class_<Result>(m, "Result")
      .def_readonly("x", &Result::x)
      .def_readonly("u", &Result::u)
      .def_readonly("lam", &Result::lambda)
      .def_readonly("mu", &Result::mu)
      .def_readonly("h", &Result::h)
      .def_readonly("info", &Result::info);
  py::enum_<Constraint::Kind>(m, "ConstraintKind")
      .value("pair", Constraint::Kind::Pair)
      .value("obstacle", Constraint::Kind::Obstacle)
      .value("state_max", Constraint::Kind::StateMax)
      .value("state_min", Constraint::Kind::StateMin)
      .value("control_max", Constraint::Kind::ControlMax)
      .value("control_min", Constraint::Kind::ControlMin);
  py::class_<Constraint>(m, "Constraint")
      .def_readonly("kind", &Constraint::kind)
      .def_readonly("i", &Constraint::i)
      .def_readonly("j", &Constraint::j)
      .def_readonly("k", &Constraint::k)
      .def_readonly("idx", &Constraint::idx);
  py::class_<Solver>(m, "Solver")
      .def(py::init<>())
      .def("setup", &Solver::setup, py::arg("problem"), py::arg("settings"))
      .def("update", &Solver::update, py::arg("problem"))
      .def("update_settings", &Solver::update_settings, py::arg("settings"))
      .def("update_initial_state", &Solver::update_initial_state, py::arg("agent"), py::arg("x0"))
      .def("update_cost", &Solver::update_cost, py::arg("agent"), py::arg("cost"))
      .def("update_lead", &Solver::update_lead, py::arg("agent"), py::arg("lead"))
      .def("update_bounds", &Solver::update_bounds, py::arg("agent"), py::arg("u_min"), py::arg("u_max"), py::arg("x_min"),
           py::arg("x_max"))
      .def("update_collision_distance", &Solver::update_collision_distance, py::arg("min_distance"), py::arg("steps"))
      .def("update_obstacle", &Solver::update_obstacle, py::arg("index"), py::arg("positions"), py::arg("min_distance"),
           py::arg("steps"))
      .def(
          "solve", [](Solver& s, const WarmStart* w) { return s.solve(w); }, py::arg("warm_start") = nullptr,
          py::call_guard<py::gil_scoped_release>())
      .def(
          "best_response", [](Solver& s, int rounds, const WarmStart* w) { return s.best_response(rounds, w); },
          py::arg("rounds"), py::arg("warm_start") = nullptr, py::call_guard<py::gil_scoped_release>())
      .def("passing_order", &Solver::passing_order, py::arg("x"), py::arg("warm_start") = nullptr)
      .def("constraints", &Solver::constraints)
      .def("structure_version", &Solver::structure_version)
      .def("column_of", &Solver::column_of, py::arg("i"), py::arg("k"), py::arg("kind"))
      .def("debug_residual", [](Solver& s, const std::vector<Mat>& x, const std::vector<Mat>& u,
                                const std::vector<Mat>& lam, const Vec& mu, double rho) {
        Vec r;
        Mat J;
        auto cols = s.debug_residual(x, u, lam, mu, rho, r, J);
        return py::make_tuple(r, J, cols);
      });
}
