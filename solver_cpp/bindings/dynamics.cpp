#include <pybind11/eigen.h>
#include <pybind11/stl.h>

#include "bindings.hpp"
#include "rd3g/dynamics.hpp"

using namespace rd3g;

void bind_dynamics(py::module_& m) {
  py::class_<Dynamics, std::shared_ptr<Dynamics>>(m, "Dynamics")
      .def_property_readonly("nx", &Dynamics::nx)
      .def_property_readonly("nu", &Dynamics::nu)
      .def_property_readonly("name", &Dynamics::name)
      .def(
          "eval",
          [](const Dynamics& d, const Vec& x, const Vec& u) {
            if (x.size() != d.nx() || u.size() != d.nu()) throw std::invalid_argument("x/u have the wrong size");
            Vec xn(d.nx());
            Mat A(d.nx(), d.nx()), B(d.nx(), d.nu());
            d.eval(x, u, xn, A, B);
            return py::make_tuple(xn, A, B);
          },
          py::arg("x"), py::arg("u"), "Returns (x_next, A = df/dx, B = df/du).")
      .def(
          "lambda_hessian",
          [](const Dynamics& d, const Vec& x, const Vec& u, const Vec& lam) {
            if (x.size() != d.nx() || u.size() != d.nu() || lam.size() != d.nx())
              throw std::invalid_argument("x/u/lambda have the wrong size");
            Mat H(d.nx() + d.nu(), d.nx() + d.nu());
            d.lambda_hessian(x, u, lam, H);
            return H;
          },
          py::arg("x"), py::arg("u"), py::arg("lam"), "Returns d^2(lam' f)/d(x,u)^2 ordered [x; u].")
      .def(
          "derivative_pattern",
          [](const Dynamics& d) {
            Pattern A, B, H;
            d.derivative_pattern(A, B, H);
            return py::make_tuple(A, B, H);
          },
          "Returns (A, B, H) boolean: the entries of df/dx, df/du and d^2(lam' f)/d(x,u)^2 that can be nonzero.")
      .def(
          "control_domain",
          [](const Dynamics& d) {
            Vec lo(d.nu()), hi(d.nu());
            d.control_domain(lo, hi);
            return py::make_tuple(lo, hi);
          },
          "Returns (lo, hi): the open box of controls on which the model is smooth (+-inf: no limit).")
      .def(
          "rollout",
          [](const Dynamics& d, const Vec& x0, const Mat& U) {
            // U: T x nu; returns (T+1) x nx. Batch helper for tools that replay logged commands.
            if (x0.size() != d.nx() || U.cols() != d.nu()) throw std::invalid_argument("x0/U have the wrong shape");
            Mat X(U.rows() + 1, d.nx());
            Vec x = x0, xn(d.nx());
            Mat A(d.nx(), d.nx()), B(d.nx(), d.nu());
            X.row(0) = x0.transpose();
            for (int k = 0; k < U.rows(); ++k) {
              d.eval(x, U.row(k).transpose(), xn, A, B);
              x = xn;
              X.row(k + 1) = x.transpose();
            }
            return X;
          },
          py::arg("x0"), py::arg("U"));
  py::class_<LinearDynamics, Dynamics, std::shared_ptr<LinearDynamics>>(m, "LinearDynamics")
      .def(py::init<Mat, Mat>(), py::arg("A"), py::arg("B"));
  py::class_<KinematicBicycle, Dynamics, std::shared_ptr<KinematicBicycle>>(m, "KinematicBicycle")
      .def(py::init<double, double, double>(), py::arg("lf"), py::arg("lr"), py::arg("dt"));
  py::class_<KinematicBicycleFrenet, Dynamics, std::shared_ptr<KinematicBicycleFrenet>>(m, "KinematicBicycleFrenet")
      .def(py::init<double, double, double, Vec, double, bool>(), py::arg("lf"), py::arg("lr"), py::arg("dt"),
           py::arg("kappa"), py::arg("ds"), py::arg("closed"))
      .def("curvature", [](const KinematicBicycleFrenet& d, double s) {
        double k, dk;
        d.curvature(s, k, dk);
        return py::make_tuple(k, dk);
      });
}
