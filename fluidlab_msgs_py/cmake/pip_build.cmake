# Loaded only when pip builds this package through scikit-build-core: pyproject.toml passes
# -DCMAKE_PROJECT_fluidlab_msgs_INCLUDE=<this file>, which CMake runs right after project(fluidlab_msgs).
# A colcon build on ROS 2 Jazzy never sets that variable and never reads this file.
#
# The ROS 2 Jazzy wheels (ros-jazzy-*) install an ament prefix (share/, lib/, include/) into the Python
# environment's prefix. Building an interface package against them needs two things that a sourced ROS
# installation would otherwise provide; both are done here, inside this build, and change no file outside it:
#   1. the ament prefixes: AMENT_PREFIX_PATH (the ament resource index, e.g. "No 'rosidl_typesupport_c'
#      found" without it) and CMAKE_PREFIX_PATH (find_package);
#   2. the wheels' exported CMake targets name the include directories of the machine the wheels were built
#      on (/opt/python/cp311-cp311/include/python3.11 and its NumPy headers); CMake refuses an imported target
#      whose include directory does not exist, so they are repointed to this interpreter's before generation.
# The install layout (CMAKE_INSTALL_PREFIX = the wheel's data directory = the environment's prefix) is set in
# pyproject.toml. See docs/ros-build.md.

if(NOT DEFINED Python_EXECUTABLE)
  message(FATAL_ERROR "pip_build.cmake is meant for scikit-build-core builds (no Python_EXECUTABLE given)")
endif()

# --- 1. ament prefixes of the build environment --------------------------------------------------------------
# pip's isolated build environment installs the build requirements under its own prefixes (overlay/, normal/);
# a --no-build-isolation build uses the target environment's prefix. A prefix is an ament prefix when it holds
# share/ament_index; find them from the site-packages directories on the interpreter's sys.path.
execute_process(
  COMMAND "${Python_EXECUTABLE}" -c [=[
import os, sys
prefixes = []
for entry in sys.path:
    parts = os.path.normpath(entry).split(os.sep)
    # <prefix>/lib/pythonX.Y/site-packages (also lib64/, dist-packages)
    if len(parts) >= 3 and parts[-1] in ('site-packages', 'dist-packages') and parts[-2].startswith('python'):
        prefix = os.sep.join(parts[:-3]) or os.sep
        if os.path.isdir(os.path.join(prefix, 'share', 'ament_index')) and prefix not in prefixes:
            prefixes.append(prefix)
print(';'.join(prefixes), end='')
]=]
  OUTPUT_VARIABLE _fluidlab_ament_prefixes
  RESULT_VARIABLE _fluidlab_result)
if(NOT _fluidlab_result EQUAL 0 OR _fluidlab_ament_prefixes STREQUAL "")
  message(FATAL_ERROR
    "No ament prefix (share/ament_index) next to the site-packages of ${Python_EXECUTABLE}: are the ros-jazzy-* "
    "build requirements of fluidlab_msgs_py/pyproject.toml installed?")
endif()
message(STATUS "fluidlab_msgs (pip build): ament prefixes ${_fluidlab_ament_prefixes}")
list(PREPEND CMAKE_PREFIX_PATH ${_fluidlab_ament_prefixes})
set(_fluidlab_env_prefixes ${_fluidlab_ament_prefixes})
if(DEFINED ENV{AMENT_PREFIX_PATH} AND NOT "$ENV{AMENT_PREFIX_PATH}" STREQUAL "")
  string(REPLACE ":" ";" _fluidlab_existing "$ENV{AMENT_PREFIX_PATH}")
  list(APPEND _fluidlab_env_prefixes ${_fluidlab_existing})
endif()
list(REMOVE_DUPLICATES _fluidlab_env_prefixes)
string(REPLACE ";" ":" _fluidlab_env_prefixes "${_fluidlab_env_prefixes}")
# Configuration reads the ament index (the typesupports to generate); the build steps get their arguments from it.
set(ENV{AMENT_PREFIX_PATH} "${_fluidlab_env_prefixes}")

# --- 2. include directories of the wheels' imported targets ----------------------------------------------------
execute_process(
  COMMAND "${Python_EXECUTABLE}" -c
    "import sysconfig, numpy; print(sysconfig.get_paths()['include'] + ';' + numpy.get_include(), end='')"
  OUTPUT_VARIABLE _fluidlab_py_includes
  RESULT_VARIABLE _fluidlab_result)
if(NOT _fluidlab_result EQUAL 0)
  message(FATAL_ERROR "Cannot read the Python and NumPy include directories of ${Python_EXECUTABLE}")
endif()
list(GET _fluidlab_py_includes 0 FLUIDLAB_PYTHON_INCLUDE_DIR)
list(GET _fluidlab_py_includes 1 FLUIDLAB_NUMPY_INCLUDE_DIR)

# Called at the end of the top-level CMakeLists.txt, after rosidl_generate_interfaces() has imported the targets
# and before CMake checks their include directories (at generation).
function(_fluidlab_repoint_include_dirs directory)
  get_property(_targets DIRECTORY "${directory}" PROPERTY IMPORTED_TARGETS)
  foreach(_target IN LISTS _targets)
    foreach(_property INTERFACE_INCLUDE_DIRECTORIES INTERFACE_SYSTEM_INCLUDE_DIRECTORIES)
      get_target_property(_dirs ${_target} ${_property})
      if(NOT _dirs)
        continue()
      endif()
      set(_new_dirs "")
      set(_changed FALSE)
      foreach(_dir IN LISTS _dirs)
        if(NOT _dir MATCHES "^\\$<" AND NOT EXISTS "${_dir}")
          if(_dir MATCHES "/include/python3\\.[0-9]+$")
            set(_dir "${FLUIDLAB_PYTHON_INCLUDE_DIR}")
            set(_changed TRUE)
          elseif(_dir MATCHES "/numpy/(_core/|core/)?include$")
            set(_dir "${FLUIDLAB_NUMPY_INCLUDE_DIR}")
            set(_changed TRUE)
          endif()
        endif()
        list(APPEND _new_dirs "${_dir}")
      endforeach()
      if(_changed)
        list(REMOVE_DUPLICATES _new_dirs)
        set_target_properties(${_target} PROPERTIES ${_property} "${_new_dirs}")
        message(DEBUG "fluidlab_msgs (pip build): ${_target} ${_property} -> ${_new_dirs}")
      endif()
    endforeach()
  endforeach()
  get_property(_subdirs DIRECTORY "${directory}" PROPERTY SUBDIRECTORIES)
  foreach(_subdir IN LISTS _subdirs)
    _fluidlab_repoint_include_dirs("${_subdir}")
  endforeach()
endfunction()
cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _fluidlab_repoint_include_dirs "${CMAKE_SOURCE_DIR}")
