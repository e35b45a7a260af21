"""C code generation for the estimators (CasADi codegen plus a small hand-written C API)."""
