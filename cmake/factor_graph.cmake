# The factor-graph view of the dynamics (src/factor_graph/, docs/factor-graph.md):
# library scandyn_factor_graph (the assembly of the graph's sparse system, always;
# the CHOLMOD solver with AMD / COLAMD / METIS / nested-dissection orderings when
# SuiteSparse is found: Debian `libsuitesparse-dev libmetis-dev`; the GPU's sparse
# Cholesky on cuSOLVER when the CUDA backend is built with cuSOLVER), its test and
# the Tables I / II program bench_factor_graph.
option(SCANDYN_FACTOR_GRAPH_CHOLMOD "Build the factor-graph sparse solvers on SuiteSparse CHOLMOD if found" ON)
set(SCANDYN_HAS_CHOLMOD OFF)
if(SCANDYN_FACTOR_GRAPH_CHOLMOD)
  find_path(CHOLMOD_INCLUDE_DIR cholmod.h PATH_SUFFIXES suitesparse)
  find_library(CHOLMOD_LIBRARY cholmod)
  find_library(SUITESPARSECONFIG_LIBRARY suitesparseconfig)
  if(CHOLMOD_INCLUDE_DIR AND CHOLMOD_LIBRARY AND SUITESPARSECONFIG_LIBRARY)
    set(SCANDYN_HAS_CHOLMOD ON)
    message(STATUS "scandyn: factor-graph solvers on CHOLMOD (${CHOLMOD_LIBRARY})")
  else()
    message(STATUS "scandyn: CHOLMOD not found (apt-get install libsuitesparse-dev libmetis-dev): "
                   "the factor graph is assembled but has no sparse solver, bench_factor_graph is not built")
  endif()
else()
  message(STATUS "scandyn: factor-graph solvers off (SCANDYN_FACTOR_GRAPH_CHOLMOD=OFF): no sparse solver, "
                 "bench_factor_graph is not built")
endif()
if(SCANDYN_HAS_CHOLMOD)
  set(SCANDYN_HAS_CHOLMOD_01 1)
else()
  set(SCANDYN_HAS_CHOLMOD_01 0)
endif()
# The GPU's sparse Cholesky (src/factor_graph/gpu_sparse_cholesky.cpp: cuSOLVER's
# csrchol, host code): with the CUDA backend and cuSOLVER, with or without CHOLMOD.
set(SCANDYN_HAS_FACTOR_GRAPH_GPU_01 0)
if(SCANDYN_CUDA AND SCANDYN_HAS_CUSOLVER AND TARGET CUDA::cusparse)
  set(SCANDYN_HAS_FACTOR_GRAPH_GPU_01 1)
  message(STATUS "scandyn: factor-graph GPU solver on cuSOLVER's sparse Cholesky")
endif()
configure_file(${PROJECT_SOURCE_DIR}/include/scandyn/factor_graph/factor_graph_config.hpp.in
               ${PROJECT_BINARY_DIR}/include/scandyn/factor_graph/factor_graph_config.hpp)

file(GLOB _scandyn_fg_sources CONFIGURE_DEPENDS ${PROJECT_SOURCE_DIR}/src/factor_graph/*.cpp)
add_library(scandyn_factor_graph STATIC ${_scandyn_fg_sources})
target_link_libraries(scandyn_factor_graph PUBLIC scandyn)
if(SCANDYN_HAS_FACTOR_GRAPH_GPU_01)
  target_link_libraries(scandyn_factor_graph PUBLIC CUDA::cusolver CUDA::cusparse)
endif()
if(SCANDYN_HAS_CHOLMOD)
  target_include_directories(scandyn_factor_graph PRIVATE ${CHOLMOD_INCLUDE_DIR})
  target_link_libraries(scandyn_factor_graph PRIVATE ${CHOLMOD_LIBRARY} ${SUITESPARSECONFIG_LIBRARY})
  add_executable(bench_factor_graph ${PROJECT_SOURCE_DIR}/bench/bench_factor_graph.cpp)
  target_link_libraries(bench_factor_graph PRIVATE scandyn_factor_graph)
  target_compile_definitions(bench_factor_graph PRIVATE SCANDYN_DEFAULT_MODELS_DIR="${PROJECT_SOURCE_DIR}/models")
  # the simulator's step of a cloth grid on the sparse loop path (docs/loops.md)
  add_executable(bench_loop_step ${PROJECT_SOURCE_DIR}/bench/bench_loop_step.cpp)
  target_link_libraries(bench_loop_step PRIVATE scandyn_factor_graph)
endif()
