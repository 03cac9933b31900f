# The fuzz harnesses as a library, shared by the libFuzzer targets (fuzz/)
# and the regression test that replays their inputs (tests/reliability/).
# Included from both; defines the target once.
if(NOT TARGET mll_fuzz_harness)
  add_library(mll_fuzz_harness STATIC
    ${CMAKE_CURRENT_LIST_DIR}/core_harness.cc
    ${CMAKE_CURRENT_LIST_DIR}/service_harness.cc)
  target_include_directories(mll_fuzz_harness PUBLIC ${CMAKE_CURRENT_LIST_DIR})
  target_link_libraries(mll_fuzz_harness PUBLIC mll::core mll::service
    absl::strings absl::synchronization)
endif()
