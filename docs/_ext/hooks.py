"""MkDocs hooks for the rigidjax site (placeholder)."""
