# cmake/pinocchio_prefix.cmake: where Pinocchio's C++ headers are, for the programs
# that compare with Pinocchio in C++ (bench/pinocchio_second_order.cpp, ctest
# pinocchio_second_order). Included by tests/ and bench/ (each directory scope
# computes the variables; the status line is printed once).
#
# SCANDYN_PINOCCHIO_PREFIX: an install prefix holding include/pinocchio (empty, the
# default: the `pin` wheel's cmeel.prefix in the project's .venv, made by
# scripts/setup_python.sh, when it is there; re-checked at every configure). Pinocchio
# is used header-only (its Boost headers come from the same prefix; Eigen is the
# project's Eigen3::Eigen); no Pinocchio library is linked.
# Sets SCANDYN_PINOCCHIO_FOUND, SCANDYN_PINOCCHIO_INCLUDE_DIR and, when not found,
# SCANDYN_PINOCCHIO_REASON.
set(SCANDYN_PINOCCHIO_PREFIX "" CACHE PATH
  "Pinocchio C++ install prefix for bench/pinocchio_second_order (empty: .venv's cmeel.prefix when present)")

set(SCANDYN_PINOCCHIO_FOUND OFF)
set(SCANDYN_PINOCCHIO_INCLUDE_DIR "")
set(_scandyn_pin_prefix "${SCANDYN_PINOCCHIO_PREFIX}")
if(NOT _scandyn_pin_prefix)
  file(GLOB _scandyn_pin_candidates LIST_DIRECTORIES true
    "${PROJECT_SOURCE_DIR}/.venv/lib/python3*/site-packages/cmeel.prefix")
  if(_scandyn_pin_candidates)
    list(GET _scandyn_pin_candidates 0 _scandyn_pin_prefix)
  endif()
endif()
if(NOT _scandyn_pin_prefix)
  set(SCANDYN_PINOCCHIO_REASON
    "no Pinocchio C++ prefix: ${PROJECT_SOURCE_DIR}/.venv has no cmeel.prefix (run scripts/setup_python.sh) and SCANDYN_PINOCCHIO_PREFIX is not set")
elseif(NOT EXISTS "${_scandyn_pin_prefix}/include/pinocchio/algorithm/rnea-second-order-derivatives.hpp")
  set(SCANDYN_PINOCCHIO_REASON
    "${_scandyn_pin_prefix} has no include/pinocchio/algorithm/rnea-second-order-derivatives.hpp")
elseif(NOT EXISTS "${_scandyn_pin_prefix}/include/boost/version.hpp")
  set(SCANDYN_PINOCCHIO_REASON "${_scandyn_pin_prefix} has no Boost headers (include/boost)")
else()
  set(SCANDYN_PINOCCHIO_FOUND ON)
  set(SCANDYN_PINOCCHIO_INCLUDE_DIR "${_scandyn_pin_prefix}/include")
  set(SCANDYN_PINOCCHIO_REASON "")
endif()
get_property(_scandyn_pin_reported GLOBAL PROPERTY SCANDYN_PINOCCHIO_REPORTED)
if(_scandyn_pin_reported)
elseif(SCANDYN_PINOCCHIO_FOUND)
  message(STATUS "Pinocchio C++ headers: ${SCANDYN_PINOCCHIO_INCLUDE_DIR} (bench/pinocchio_second_order)")
else()
  message(STATUS "bench/pinocchio_second_order not built: ${SCANDYN_PINOCCHIO_REASON}")
endif()
set_property(GLOBAL PROPERTY SCANDYN_PINOCCHIO_REPORTED ON)
