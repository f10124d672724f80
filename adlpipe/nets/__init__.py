"""Networks only; the objectives (flow matching, DDPM, MSE) live in adlpipe.objectives."""
