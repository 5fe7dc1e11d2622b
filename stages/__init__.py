"""The pipeline's stages, one module each; every stage is a function from typed inputs to a
frozen ``*Result``. Only ``pipeline.runtime.orchestrator`` imports them and wires them in order."""
