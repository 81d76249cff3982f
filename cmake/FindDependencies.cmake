# Every find_package of the project lives here, so a module's CMakeLists only names targets.
# All of them come from Debian packages (scripts/install-deps.sh) or PyPI (pybind11); nothing is downloaded.

find_package(Eigen3 3.4 REQUIRED NO_MODULE)
find_package(nlohmann_json 3.10 REQUIRED)
find_package(Threads REQUIRED)
find_package(Ceres 2.1 REQUIRED)
find_package(yaml-cpp REQUIRED)

if(TRACKCAL_BUILD_TESTS)
  find_package(GTest REQUIRED)
endif()

if(TRACKCAL_BUILD_BENCHMARKS)
  find_package(benchmark REQUIRED)
endif()

if(TRACKCAL_BUILD_PYTHON)
  find_package(Python 3.9 REQUIRED COMPONENTS Interpreter Development.Module)
  if(NOT pybind11_DIR)
    execute_process(
      COMMAND "${Python_EXECUTABLE}" -m pybind11 --cmakedir
      OUTPUT_VARIABLE pybind11_DIR
      OUTPUT_STRIP_TRAILING_WHITESPACE
      RESULT_VARIABLE pybind11_rc)
    if(NOT pybind11_rc EQUAL 0)
      message(FATAL_ERROR "pybind11 is not installed for ${Python_EXECUTABLE}; run scripts/install-deps.sh")
    endif()
  endif()
  find_package(pybind11 2.10 CONFIG REQUIRED)
endif()
