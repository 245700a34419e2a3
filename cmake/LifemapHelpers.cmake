# Small helpers so every lifemap target gets the same flags (Abseil-style).
#
#   lifemap_library(NAME core_common SRCS a.cc b.cc DEPS PUBLIC x PRIVATE y)
#   lifemap_executable(NAME lifemapd SRCS main.cc DEPS ...)
#   lifemap_test(NAME core_common_test SRCS a_test.cc DEPS core_common)
#   lifemap_precompile(lifemap_cli_lib <CLI/CLI.hpp> ${PROJECT_SOURCE_DIR}/client/x.h)

set(LIFEMAP_WARNINGS -Wall -Wextra -Wpedantic -Wshadow -Wnon-virtual-dtor -Wold-style-cast
                     -Wcast-align -Woverloaded-virtual -Wformat=2)
if(LIFEMAP_WERROR)
  list(APPEND LIFEMAP_WARNINGS -Werror)
endif()

function(_lifemap_apply_common target)
  target_compile_options(${target} PRIVATE ${LIFEMAP_WARNINGS})
  target_include_directories(${target} PUBLIC ${PROJECT_SOURCE_DIR})
endfunction()

function(lifemap_library)
  cmake_parse_arguments(L "" "NAME" "SRCS;PUBLIC_DEPS;PRIVATE_DEPS" ${ARGN})
  add_library(${L_NAME} STATIC ${L_SRCS})
  _lifemap_apply_common(${L_NAME})
  target_link_libraries(${L_NAME} PUBLIC ${L_PUBLIC_DEPS} PRIVATE ${L_PRIVATE_DEPS})
endfunction()

function(lifemap_executable)
  cmake_parse_arguments(L "" "NAME;OUTPUT_NAME" "SRCS;DEPS" ${ARGN})
  add_executable(${L_NAME} ${L_SRCS})
  _lifemap_apply_common(${L_NAME})
  target_link_libraries(${L_NAME} PRIVATE ${L_DEPS})
  if(L_OUTPUT_NAME)
    set_target_properties(${L_NAME} PROPERTIES OUTPUT_NAME ${L_OUTPUT_NAME})
  endif()
  set_target_properties(${L_NAME} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${PROJECT_BINARY_DIR}/bin)
endfunction()

# A GoogleTest binary; its tests are registered with CTest one by one. LABELS lets CTest select
# unit / integration / e2e suites (ctest -L unit).
function(lifemap_test)
  cmake_parse_arguments(L "" "NAME;LABEL" "SRCS;DEPS" ${ARGN})
  add_executable(${L_NAME} ${L_SRCS})
  _lifemap_apply_common(${L_NAME})
  target_link_libraries(${L_NAME} PRIVATE ${L_DEPS} GTest::gtest GTest::gmock GTest::gtest_main)
  target_compile_definitions(${L_NAME} PRIVATE
    LIFEMAP_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    LIFEMAP_BINARY_DIR="${PROJECT_BINARY_DIR}")
  if(NOT L_LABEL)
    set(L_LABEL unit)
  endif()
  # End-to-end and integration tests render worlds and stream whole recordings (the loop
  # closure test 600 frames): up to 10 min each on a loaded 2-core machine (ctest --timeout only
  # sets the default for tests without their own).
  set(timeout 300)
  if(L_LABEL STREQUAL "e2e" OR L_LABEL STREQUAL "integration")
    set(timeout 600)
  endif()
  gtest_discover_tests(${L_NAME} PROPERTIES LABELS ${L_LABEL} TIMEOUT ${timeout}
                       DISCOVERY_TIMEOUT 60)
endfunction()

# Precompiles headers most of a target's files include (LIFEMAP_PCH): gRPC, Protobuf, OpenCV,
# Eigen, CLI11 and nlohmann::json headers take 1-2.5 s each to parse, ~8 s a file in the
# services and the CLI, paid once per target instead of once per file. Only for targets of
# many files that share them (a precompiled header costs one parse itself). With
# -DLIFEMAP_PCH=OFF every file must compile from its own includes (scripts/fuzz builds so).
function(lifemap_precompile target)
  if(LIFEMAP_PCH)
    target_precompile_headers(${target} PRIVATE ${ARGN})
  endif()
endfunction()
