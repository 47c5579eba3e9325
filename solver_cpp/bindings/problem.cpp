#include <pybind11/eigen.h>
#include <pybind11/stl.h>

#include "bindings.hpp"
#include "rd3g/problem.hpp"

using namespace rd3g;

void bind_problem(py::module_& m) {
  py::class_<QuadraticCost>(m, "QuadraticCost")
      .def(py::init<>())
      .def_readwrite("x_ref", &QuadraticCost::x_ref)
      .def_readwrite("x_ref_steps", &QuadraticCost::x_ref_steps)
      .def_readwrite("Q_ref", &QuadraticCost::Q_ref)
      .def_readwrite("Q", &QuadraticCost::Q)
      .def_readwrite("R", &QuadraticCost::R)
      .def_readwrite("Qf_ref", &QuadraticCost::Qf_ref)
      .def_readwrite("Qf", &QuadraticCost::Qf);
  py::class_<LeadCost>(m, "LeadCost")
      .def(py::init<>())
      .def_readwrite("weight", &LeadCost::weight)
      .def_readwrite("index", &LeadCost::index);
  py::enum_<CollisionForm>(m, "CollisionForm")
      .value("distance", CollisionForm::Distance)
      .value("squared", CollisionForm::Squared);
  py::class_<PairDistance>(m, "PairDistance")
      .def(py::init<>())
      .def_readwrite("i", &PairDistance::i)
      .def_readwrite("j", &PairDistance::j)
      .def_readwrite("min_distance", &PairDistance::min_distance)
      .def_readwrite("min_distance_steps", &PairDistance::min_distance_steps);
  py::class_<CollisionSpec>(m, "CollisionSpec")
      .def(py::init<>())
      .def_readwrite("enabled", &CollisionSpec::enabled)
      .def_readwrite("min_distance", &CollisionSpec::min_distance)
      .def_readwrite("min_distance_steps", &CollisionSpec::min_distance_steps)
      .def_readwrite("pair_distances", &CollisionSpec::pair_distances)
      .def_readwrite("form", &CollisionSpec::form)
      .def_readwrite("pos_x", &CollisionSpec::pos_x)
      .def_readwrite("pos_y", &CollisionSpec::pos_y)
      .def_readwrite("pos_x_scale_steps", &CollisionSpec::pos_x_scale_steps);
  py::class_<Obstacle>(m, "Obstacle")
      .def(py::init<>())
      .def_readwrite("positions", &Obstacle::positions)
      .def_readwrite("min_distance", &Obstacle::min_distance)
      .def_readwrite("min_distance_steps", &Obstacle::min_distance_steps);
  py::class_<Problem>(m, "Problem")
      .def(py::init<>())
      .def_readwrite("horizon", &Problem::horizon)
      .def_readwrite("dt", &Problem::dt)
      .def_readwrite("dynamics", &Problem::dynamics)
      .def_readwrite("x0", &Problem::x0)
      .def_readwrite("costs", &Problem::costs)
      .def_readwrite("lead", &Problem::lead)
      .def_readwrite("collision", &Problem::collision)
      .def_readwrite("u_min", &Problem::u_min)
      .def_readwrite("u_max", &Problem::u_max)
      .def_readwrite("x_min", &Problem::x_min)
      .def_readwrite("x_max", &Problem::x_max)
      .def_readwrite("obstacles", &Problem::obstacles);
}
