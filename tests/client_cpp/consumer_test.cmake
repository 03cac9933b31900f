# The installed-package test: installs the programs (mll_server, mll_cli) and
# the client component into a fresh prefix, configures and builds
# tests/client_cpp/consumer against it with find_package(MultiLunarLander),
# then runs it against a real server. The same project also builds the C++ and
# CMake code blocks of the documents (doc_blocks.cmake), so that every one of
# them compiles and links against the installed package as a user would.
# Inputs (-D): BUILD_DIR, SOURCE_DIR, DOCS_ROOT (the repository, whose
# README.md and docs/*.md are read), WORK_DIR, GENERATOR, RUN_WITH_SERVER,
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
run(doc_blocks ${CMAKE_COMMAND} -DSOURCE_ROOT=${DOCS_ROOT}
    -DOUT_DIR=${WORK_DIR}/doc_blocks -P ${CMAKE_CURRENT_LIST_DIR}/doc_blocks.cmake)
run(configure ${CMAKE_COMMAND} -S ${SOURCE_DIR} -B ${WORK_DIR}/build
    -G ${GENERATOR} -DCMAKE_PREFIX_PATH=${prefix} -DCMAKE_BUILD_TYPE=Release
    -DMLL_DOC_BLOCKS_DIR=${WORK_DIR}/doc_blocks)
run(build ${CMAKE_COMMAND} --build ${WORK_DIR}/build)
run(run ${RUN_WITH_SERVER} ${SERVER} ${WORK_DIR}/build/consumer)
