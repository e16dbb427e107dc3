# ConsumerTest.cmake: checks the exported CMake package end to end.
#
#   cmake -DSCANDYN_BUILD_DIR=<build> -DCONSUMER_SOURCE_DIR=<tests/consumer>
#         -DWORK_DIR=<scratch> [-DCONSUMER_GENERATOR=Ninja] [-DCONSUMER_BUILD_TYPE=Release]
#         [-DCONSUMER_CXX_COMPILER=...] [-DCONSUMER_CXX_FLAGS=...]
#         [-DCONSUMER_PREFIX_PATH=a|b] [-DCONSUMER_CUDA_ROOT=/usr/local/cuda]
#         -P ConsumerTest.cmake
#
# 1. cmake --install <build> --prefix <scratch>/prefix
# 2. configure <tests/consumer> with find_package(scandyn) pointed at that prefix
#    (and nothing from the build tree), build it and run it.
# Lists (CONSUMER_PREFIX_PATH) use '|' in place of ';'.
cmake_minimum_required(VERSION 3.20)

foreach(var SCANDYN_BUILD_DIR CONSUMER_SOURCE_DIR WORK_DIR)
  if(NOT DEFINED ${var} OR "${${var}}" STREQUAL "")
    message(FATAL_ERROR "ConsumerTest.cmake: -D${var}=... is required")
  endif()
endforeach()
if(NOT CONSUMER_GENERATOR)
  set(CONSUMER_GENERATOR Ninja)
endif()
if(NOT CONSUMER_BUILD_TYPE)
  set(CONSUMER_BUILD_TYPE Release)
endif()

function(run_step what)
  message(STATUS "consumer test: ${what}: ${ARGN}")
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE rc)
  if(NOT rc EQUAL 0)
    message(FATAL_ERROR "consumer test: ${what} failed (${rc})")
  endif()
endfunction()

set(prefix "${WORK_DIR}/prefix")
set(build "${WORK_DIR}/build")
file(REMOVE_RECURSE "${WORK_DIR}")
file(MAKE_DIRECTORY "${WORK_DIR}")

# 1. install
run_step("install" "${CMAKE_COMMAND}" --install "${SCANDYN_BUILD_DIR}" --prefix "${prefix}"
         --config "${CONSUMER_BUILD_TYPE}")
file(GLOB_RECURSE _configs "${prefix}/*/scandynConfig.cmake")
if(NOT _configs)
  message(FATAL_ERROR "consumer test: no scandynConfig.cmake under ${prefix}")
endif()
foreach(f "include/scandyn/build_config.hpp" "include/scandyn/spatial.hpp"
          "include/scandyn/algorithm/reference.hpp" "include/scandyn/model/load.hpp")
  if(NOT EXISTS "${prefix}/${f}")
    message(FATAL_ERROR "consumer test: ${f} was not installed")
  endif()
endforeach()

# 2. configure, build, run the consumer
string(REPLACE "|" ";" _prefix_path "${prefix}|${CONSUMER_PREFIX_PATH}")
set(args -S "${CONSUMER_SOURCE_DIR}" -B "${build}" -G "${CONSUMER_GENERATOR}"
         "-DCMAKE_BUILD_TYPE=${CONSUMER_BUILD_TYPE}"
         "-DCMAKE_PREFIX_PATH=${_prefix_path}"
         # only the installed copy may satisfy find_package(scandyn)
         "-Dscandyn_ROOT=${prefix}"
         -DCMAKE_FIND_USE_PACKAGE_REGISTRY=OFF)
if(CONSUMER_CXX_COMPILER)
  list(APPEND args "-DCMAKE_CXX_COMPILER=${CONSUMER_CXX_COMPILER}")
endif()
if(CONSUMER_CXX_FLAGS)
  list(APPEND args "-DCMAKE_CXX_FLAGS=${CONSUMER_CXX_FLAGS}"
                   "-DCMAKE_EXE_LINKER_FLAGS=${CONSUMER_CXX_FLAGS}")
endif()
if(CONSUMER_CUDA_ROOT)
  list(APPEND args "-DCUDAToolkit_ROOT=${CONSUMER_CUDA_ROOT}")
endif()
run_step("configure" "${CMAKE_COMMAND}" ${args})
run_step("build" "${CMAKE_COMMAND}" --build "${build}" --config "${CONSUMER_BUILD_TYPE}")

set(_consumer "${build}/scandyn_consumer")
if(NOT EXISTS "${_consumer}")
  set(_consumer "${build}/${CONSUMER_BUILD_TYPE}/scandyn_consumer")  # multi-config generators
endif()
if(NOT EXISTS "${_consumer}")
  message(FATAL_ERROR "consumer test: the consumer program was not built under ${build}")
endif()
run_step("run" "${_consumer}")
message(STATUS "consumer test: passed")
