"""skinsafe.core: the headless library and application, as subpackages that read as the pipeline.

skin <- robot <- design <- sim <- safety <- learn <- experiments, bench <- app; a lower layer never
imports a higher one, and only `app` (the composition root) reaches `exporters` and `hardware`
(import-linter contracts in pyproject.toml, run by `make test`). Never imports bpy.
"""
