#include <Eigen/Dense>
namespace rd3g { double build_check() { return Eigen::Vector2d(3, 4).norm(); } }
