import os
import subprocess
import sys

import pytest

from torchcbf._compile import _trust_reported_isa

inductor = pytest.importorskip("torch._inductor.cpu_vec_isa")

_PICK = """
import sys
from torch._inductor import cpu_vec_isa
from torchcbf._compile import _trust_reported_isa
if sys.argv[1] == "trust":
    with _trust_reported_isa():
        isa = cpu_vec_isa.pick_vec_isa()
else:
    isa = cpu_vec_isa.pick_vec_isa()
print(str(isa), isa.build_arch_flags())
"""


def test_trusted_isa_is_restored_after_the_call():
    from torch._inductor import config

    probe = inductor.VecISA.check_build
    with _trust_reported_isa():
        assert config.cpp.vec_isa_ok is True
        assert inductor.VecISA.check_build is not probe
    assert inductor.VecISA.check_build is probe
    assert config.cpp.vec_isa_ok is None


def test_trusted_isa_matches_the_probed_one(tmp_path):
    # each choice in a fresh process: inductor computes the list once per process
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(tmp_path)}
    env.pop("TORCHINDUCTOR_VEC_ISA_OK", None)
    picked = [
        subprocess.run(
            [sys.executable, "-c", _PICK, mode], env=env, capture_output=True, text=True, check=True
        ).stdout
        for mode in ("probe", "trust")
    ]
    assert picked[0] == picked[1]
