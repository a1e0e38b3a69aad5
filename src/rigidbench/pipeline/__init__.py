"""Pipeline stages driven by the command line (render, ...); each imports its heavy dependencies lazily."""
