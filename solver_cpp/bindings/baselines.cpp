// Bindings of the baseline game solvers (iLQGames, ALGames) and the LQ feedback game solver.
#include <pybind11/eigen.h>
#include <pybind11/stl.h>

#include "bindings.hpp"
#include "rd3g/algames.hpp"
#include "rd3g/ilqgames.hpp"

using namespace rd3g;

void bind_baselines(py::module_& m) {
  py::class_<ILQGamesSettings> is(m, "ILQGamesSettings");
  is.def(py::init<>());
#define RW(f) is.def_readwrite(#f, &ILQGamesSettings::f)
  RW(tol); RW(max_iter); RW(time_limit); RW(max_state_change); RW(ls_beta); RW(ls_max_steps); RW(violation_tol);
  RW(rho_init); RW(rho_growth); RW(rho_max); RW(round_max_iter); RW(bounds); RW(verbose);
#undef RW
  py::class_<ALGamesSettings> as(m, "ALGamesSettings");
  as.def(py::init<>());
#define RW(f) as.def_readwrite(#f, &ALGamesSettings::f)
  RW(tol); RW(max_iter); RW(time_limit); RW(violation_tol); RW(dynamics_tol); RW(rho_init); RW(rho_growth); RW(rho_max);
  RW(inner_max_iter); RW(ls_alpha); RW(ls_beta); RW(ls_max_steps); RW(bounds); RW(verbose);
#undef RW
  py::class_<ILQGamesSolver>(m, "ILQGamesSolver")
      .def(py::init<>())
      .def("setup", &ILQGamesSolver::setup, py::arg("problem"), py::arg("settings"))
      .def(
          "solve", [](ILQGamesSolver& s, const WarmStart* w) { return s.solve(w); }, py::arg("warm_start") = nullptr,
          py::call_guard<py::gil_scoped_release>())
      .def("constraints", &ILQGamesSolver::constraints);
  py::class_<ALGamesSolver>(m, "ALGamesSolver")
      .def(py::init<>())
      .def("setup", &ALGamesSolver::setup, py::arg("problem"), py::arg("settings"))
      .def(
          "solve", [](ALGamesSolver& s, const WarmStart* w) { return s.solve(w); }, py::arg("warm_start") = nullptr,
          py::call_guard<py::gil_scoped_release>())
      .def("constraints", &ALGamesSolver::constraints);
  m.def(
      "lq_feedback_game",
      [](std::vector<int> control_dims, std::vector<Mat> A, std::vector<Mat> B, std::vector<std::vector<Mat>> Q,
         std::vector<std::vector<Vec>> l, std::vector<std::vector<Mat>> R, std::vector<std::vector<Vec>> r,
         std::vector<Mat> QT, std::vector<Vec> lT) {
        const int T = static_cast<int>(A.size()), N = static_cast<int>(control_dims.size());
        if (T < 1 || N < 1) throw std::invalid_argument("A needs at least one stage and control_dims one player");
        const int n = static_cast<int>(A[0].rows());
        int m = 0;
        for (int d : control_dims) m += d;
        auto check = [](bool ok, const std::string& what) {
          if (!ok) throw std::invalid_argument(what);
        };
        check(B.size() == A.size() && Q.size() == A.size() && l.size() == A.size() && R.size() == A.size() &&
                  r.size() == A.size(), "A, B, Q, l, R, r must all have T stages");
        check(static_cast<int>(QT.size()) == N && static_cast<int>(lT.size()) == N, "QT, lT need one entry per player");
        for (int k = 0; k < T; ++k) {
          const std::string s = "[" + std::to_string(k) + "]";
          check(A[k].rows() == n && A[k].cols() == n, "A" + s + " must be n x n");
          check(B[k].rows() == n && B[k].cols() == m, "B" + s + " must be n x sum(control_dims)");
          check(static_cast<int>(Q[k].size()) == N && static_cast<int>(l[k].size()) == N &&
                    static_cast<int>(R[k].size()) == N && static_cast<int>(r[k].size()) == N,
                "Q, l, R, r" + s + " need one entry per player");
          for (int i = 0; i < N; ++i)
            check(Q[k][i].rows() == n && Q[k][i].cols() == n && l[k][i].size() == n && R[k][i].rows() == m &&
                      R[k][i].cols() == m && r[k][i].size() == m,
                  "Q/l/R/r" + s + "[" + std::to_string(i) + "] have the wrong shape");
        }
        for (int i = 0; i < N; ++i)
          check(QT[i].rows() == n && QT[i].cols() == n && lT[i].size() == n, "QT/lT[" + std::to_string(i) + "] have the wrong shape");
        LQGame g{control_dims, A, B, Q, l, R, r, QT, lT};
        LQGameSolver s;
        s.setup(n, control_dims, T);
        if (!s.solve(g)) throw std::runtime_error("LQ game: singular coupled system at some stage");
        return py::make_tuple(s.P(), s.alpha());
      },
      py::arg("control_dims"), py::arg("A"), py::arg("B"), py::arg("Q"), py::arg("l"), py::arg("R"), py::arg("r"),
      py::arg("QT"), py::arg("lT"),
      "Feedback Nash equilibrium of a finite-horizon LQ game (coupled Riccati recursion). Returns (P, alpha): "
      "per stage the joint gains of u_k = -P_k x_k - alpha_k.");
}
