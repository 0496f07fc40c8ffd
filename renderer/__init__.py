"""The renderer: G-PT on Mitsuba 3 (docs/renderer.md).

Importing it names a suitable libLLVM for Dr.Jit before anything imports Dr.Jit (renderer/variant.py): Dr.Jit
reads ``DRJIT_LIBLLVM_PATH`` once, when it is imported.
"""

from gradsep.renderer.variant import point_drjit_at_llvm

point_drjit_at_llvm()
