"""lsbench: build, trace, verify and profile GPU ray-tracing acceleration structures (grid, SVO,
ESVO and the adaptive Line Space of Delgado Krämer 2019) on GLSL and OpenCL, checked against Embree.

Data flow, one sub-package per stage: inputs (scenario -> case -> scene/rays) -> backends (build,
trace on the device) -> oracle (Embree, verify) -> running (one case, workers, resume) ->
results (records, run store) -> report / compare; commands/ holds one file per subcommand."""
