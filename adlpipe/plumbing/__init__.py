"""How a stage runs, whatever it computes: atomic outputs, locks, the resume journal, DVC-owned outputs, the command
line, user-facing errors, devices (runtime) and worker pools."""
