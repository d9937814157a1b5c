"""phantoms: see the README and docs/ for what this package does."""
