# The installed-package test: installs the programs (mll_server, mll_cli) and
# the client component into a fresh prefix, configures and builds
# tests/client_cpp/consumer against it with find_package(MultiLunarLander),
# then runs it against a real server.
# Inputs (-D): BUILD_DIR, SOURCE_DIR, WORK_DIR, GENERATOR, RUN_WITH_SERVER,
# SERVER.
file(REMOVE_RECURSE ${WORK_DIR})
set(prefix ${WORK_DIR}/install)

function(run step)
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE result)
  if(NOT result EQUAL 0)
    message(FATAL_ERROR "consumer test: ${step} failed (${result}): ${ARGN}")
  endif()
endfunction()

run(install_programs ${CMAKE_COMMAND} --install ${BUILD_DIR} --prefix ${prefix}
    --component mll_programs)
run(install ${CMAKE_COMMAND} --install ${BUILD_DIR} --prefix ${prefix}
    --component mll_client)
foreach(file bin/mll_server bin/mll_cli include/mll/client.h
        lib/cmake/MultiLunarLander/MultiLunarLanderConfig.cmake)
  if(NOT EXISTS ${prefix}/${file})
    message(FATAL_ERROR "consumer test: ${file} was not installed")
  endif()
endforeach()
run(configure ${CMAKE_COMMAND} -S ${SOURCE_DIR} -B ${WORK_DIR}/build
    -G ${GENERATOR} -DCMAKE_PREFIX_PATH=${prefix} -DCMAKE_BUILD_TYPE=Release)
run(build ${CMAKE_COMMAND} --build ${WORK_DIR}/build)
run(run ${RUN_WITH_SERVER} ${SERVER} ${WORK_DIR}/build/consumer)
