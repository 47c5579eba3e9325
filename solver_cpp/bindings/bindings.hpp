#pragma once
#include <pybind11/pybind11.h>
namespace py = pybind11;
void bind_dynamics(py::module_& m);
void bind_problem(py::module_& m);
void bind_settings(py::module_& m);
void bind_solver(py::module_& m);
void bind_baselines(py::module_& m);
