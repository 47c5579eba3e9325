#include "bindings.hpp"

PYBIND11_MODULE(_core, m) {
  m.doc() = "RD3G C++ core: dynamics models, game problem, settings and the Newton solver";
  bind_dynamics(m);
  bind_problem(m);
  bind_settings(m);
  bind_solver(m);
  bind_baselines(m);
}
