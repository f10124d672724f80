"""The seed's Table 2 benchmarks beside the ADL world (adlpipe.sim): Push-T and Franka Kitchen, each a module with one
small interface (make_env, run_policy, reference, REFERENCES, demonstrate) that the benchmark runs (registry)."""
