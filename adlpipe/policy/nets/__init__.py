"""Networks only; the objectives (flow matching, DDPM, MSE) live in adlpipe.policy.objectives."""
