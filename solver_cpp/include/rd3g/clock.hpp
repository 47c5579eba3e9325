// The solvers' wall clock (Info timings, time limits): one definition for RD3G and the baselines.
#pragma once
#include <chrono>

namespace rd3g {

using Clock = std::chrono::steady_clock;
inline double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

}  // namespace rd3g
