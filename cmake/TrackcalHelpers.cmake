# Project helpers: every module declares its targets with these, so warnings, include paths and test
# names are set in one place.
#
#   trackcal_add_library(NAME trackcal_core SRCS a.cc b.h PUBLIC_LINK_LIBS Eigen3::Eigen ...)
#   trackcal_add_executable(NAME trackcal-fit SRCS main.cc LINK_LIBS trackcal_fit [INSTALL])
#   trackcal_add_test(NAME polynomial_test SRCS polynomial_test.cc LINK_LIBS trackcal_core)
#     -> ctest name "<module>/polynomial_test", where <module> is the folder below the source root.

include(CMakeParseArguments)

set(TRACKCAL_WARNING_FLAGS -Wall -Wextra)

function(trackcal_set_common_options target)
  target_compile_options(${target} PRIVATE ${TRACKCAL_WARNING_FLAGS})
  # Headers are included as "core/pose.h", "sim/field.h": the source root is the include root.
  target_include_directories(${target} PUBLIC
    $<BUILD_INTERFACE:${PROJECT_SOURCE_DIR}>
    $<BUILD_INTERFACE:${PROJECT_BINARY_DIR}>)
endfunction()

function(trackcal_add_library)
  cmake_parse_arguments(ARG "" "NAME" "SRCS;PUBLIC_LINK_LIBS;PRIVATE_LINK_LIBS" ${ARGN})
  add_library(${ARG_NAME} STATIC ${ARG_SRCS})
  trackcal_set_common_options(${ARG_NAME})
  target_link_libraries(${ARG_NAME} PUBLIC ${ARG_PUBLIC_LINK_LIBS} PRIVATE ${ARG_PRIVATE_LINK_LIBS})
endfunction()

function(trackcal_add_executable)
  cmake_parse_arguments(ARG "INSTALL" "NAME" "SRCS;LINK_LIBS" ${ARGN})
  add_executable(${ARG_NAME} ${ARG_SRCS})
  trackcal_set_common_options(${ARG_NAME})
  target_link_libraries(${ARG_NAME} PRIVATE ${ARG_LINK_LIBS})
  if(ARG_INSTALL)
    if(DEFINED SKBUILD_SCRIPTS_DIR)
      # pip install puts the command-line tools on the environment's PATH.
      install(TARGETS ${ARG_NAME} DESTINATION "${SKBUILD_SCRIPTS_DIR}")
    else()
      install(TARGETS ${ARG_NAME} RUNTIME DESTINATION bin)
    endif()
  endif()
endfunction()

function(trackcal_module_name out_var)
  file(RELATIVE_PATH rel "${PROJECT_SOURCE_DIR}" "${CMAKE_CURRENT_SOURCE_DIR}")
  set(${out_var} "${rel}" PARENT_SCOPE)
endfunction()

function(trackcal_add_test)
  if(NOT TRACKCAL_BUILD_TESTS)
    return()
  endif()
  cmake_parse_arguments(ARG "" "NAME;TIMEOUT" "SRCS;LINK_LIBS;LABELS" ${ARGN})
  trackcal_module_name(module)
  string(REPLACE "/" "_" target_prefix "${module}")
  set(target "${target_prefix}_${ARG_NAME}")
  if(NOT ARG_TIMEOUT)
    set(ARG_TIMEOUT 300)
  endif()
  add_executable(${target} ${ARG_SRCS})
  trackcal_set_common_options(${target})
  target_link_libraries(${target} PRIVATE ${ARG_LINK_LIBS} trackcal_test_main)
  add_test(NAME "${module}/${ARG_NAME}" COMMAND ${target})
  set_tests_properties("${module}/${ARG_NAME}" PROPERTIES
    ENVIRONMENT "TRACKCAL_SOURCE_DIR=${PROJECT_SOURCE_DIR};TRACKCAL_BINARY_DIR=${PROJECT_BINARY_DIR}"
    TIMEOUT ${ARG_TIMEOUT})
  if(ARG_LABELS)
    set_tests_properties("${module}/${ARG_NAME}" PROPERTIES LABELS "${ARG_LABELS}")
  endif()
endfunction()

function(trackcal_add_benchmark)
  if(NOT TRACKCAL_BUILD_BENCHMARKS)
    return()
  endif()
  cmake_parse_arguments(ARG "" "NAME" "SRCS;LINK_LIBS;SMOKE_ARGS" ${ARGN})
  add_executable(${ARG_NAME} ${ARG_SRCS})
  trackcal_set_common_options(${ARG_NAME})
  target_link_libraries(${ARG_NAME} PRIVATE ${ARG_LINK_LIBS} benchmark::benchmark)
  # SMOKE_ARGS: ctest `bench/<name>` runs the program once with these arguments (label `bench`),
  # so that a benchmark the docs quote keeps running; keep it to a second or so (no figures).
  if(ARG_SMOKE_ARGS AND TRACKCAL_BUILD_TESTS)
    add_test(NAME "bench/${ARG_NAME}" COMMAND ${ARG_NAME} ${ARG_SMOKE_ARGS})
    set_tests_properties("bench/${ARG_NAME}" PROPERTIES
      ENVIRONMENT "TRACKCAL_SOURCE_DIR=${PROJECT_SOURCE_DIR};TRACKCAL_BINARY_DIR=${PROJECT_BINARY_DIR}"
      LABELS bench TIMEOUT 120)
  endif()
endfunction()
