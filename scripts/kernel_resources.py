"""Registers, stack (spills) and SASS instructions of the QP's Triton kernel for a GPU
architecture, compiled on a machine without a GPU (Triton's own ptxas and cuobjdump), with
the size of its longest loop (the active-set steps) and the spills inside it.

The figures a device session would read from a launch, before it: how each launch setting
of ``scripts/device_kernels.py`` compiles for the filter's QP (3 variables, 13 rows) or any
other size. Needs Triton (``pip install triton``, or ``PYTHONPATH`` to an unpacked wheel);
it compiles for NVIDIA's sm_90 (H100, H200) unless told otherwise.

    python scripts/kernel_resources.py
    python scripts/kernel_resources.py --arch 90 --vars 4 --rows 8 --dtypes float64
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parent
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))

_INTS = {"active_ptr": "*i8", "ok_ptr": "*i8", "iters_ptr": "*i64", "s_ptr": "*i64"}


def compile_kernel(
    dtype: str, N: int, M: int, setting: tuple, arch: int, *, batch: int, max_iter: int = 50
):  # noqa: ANN201
    """Triton's compiled kernel (its ``asm`` holds ``cubin``) for one size and setting, as a
    launch on ``batch`` problems compiles it: Triton's launcher marks a pointer aligned to 16
    bytes (torch's allocations are) and an integer divisible by 16 (where the kernel lets it
    specialise that argument) as such, and the compiler lays out its loads by these hints."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from torchcbf.qp import _dual_triton

    fn = _dual_triton._dual_solve_kernel
    real = {"float32": "fp32", "float64": "fp64"}[dtype]
    ints = {"B": batch, "max_iter": max_iter} | dict.fromkeys(_dual_triton.STRIDE_ARGS, 1)
    signature, attrs = {}, {}
    for i, param in enumerate(fn.params):
        name = param.name
        if name.endswith("_ptr"):
            signature[name] = _INTS.get(name, "*" + real)
            if not param.do_not_specialize_on_alignment:
                attrs[(i,)] = [["tt.divisibility", 16]]
        elif name in ints:
            signature[name] = "i32"
            if not param.do_not_specialize and ints[name] % 16 == 0:
                attrs[(i,)] = [["tt.divisibility", 16]]
        elif name in ("eps", "mach", "piv_tol", "tiny"):
            signature[name] = real
        else:
            signature[name] = "constexpr"
    block, warps, maxnreg = setting
    values = {"N": N, "M": M, "NP": _dual_triton.tile(N), "MP": _dual_triton.tile(M)}
    values["BLOCK"] = block
    constexprs = {(fn.arg_names.index(k),): v for k, v in values.items()}
    options: dict[str, int] = {"num_warps": warps}
    if maxnreg is not None:
        options["maxnreg"] = maxnreg
    source = ASTSource(fn=fn, signature=signature, constexprs=constexprs, attrs=attrs)
    return triton.compile(source, target=GPUTarget("cuda", arch, 32), options=options)


def resources(cubin: bytes) -> dict[str, int]:
    """Registers, stack bytes, SASS instructions and local loads and stores of a cubin."""
    import triton

    tools = Path(triton.__file__).parent / "backends" / "nvidia" / "bin"
    with tempfile.NamedTemporaryFile(suffix=".cubin") as fh:
        fh.write(cubin)
        fh.flush()
        usage = subprocess.run(
            [tools / "cuobjdump", "-res-usage", fh.name], capture_output=True, text=True, check=True
        ).stdout
        sass = subprocess.run(
            [tools / "cuobjdump", "-sass", fh.name], capture_output=True, text=True, check=True
        ).stdout
    found = dict(re.findall(r"(REG|STACK):(\d+)", usage))
    code = []  # (address, instruction) of each SASS line
    for line in sass.splitlines():
        at = re.match(r"\s+/\*([0-9a-f]{4,})\*/", line)
        if at:
            code.append((int(at.group(1), 16), line))
    # the longest loop: the span from a backward branch's target to the branch
    loop: list[str] = []
    for address, line in code:
        target = re.search(r"BRA.*?0x([0-9a-f]+)", line)
        if target and int(target.group(1), 16) < address:
            body = [ln for a, ln in code if int(target.group(1), 16) <= a <= address]
            loop = body if len(body) > len(loop) else loop
    lines = [line for _, line in code]
    return {
        "regs": int(found.get("REG", -1)),
        "stack": int(found.get("STACK", -1)),
        "sass": len(lines),
        "ldl": sum("LDL" in line for line in lines),
        "stl": sum("STL" in line for line in lines),
        "loop": len(loop),
        "loop_ldl": sum("LDL" in line for line in loop),
        "loop_stl": sum("STL" in line for line in loop),
    }


def main() -> int:
    from device_kernels import parse_settings

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arch", type=int, default=90, help="compute capability x 10")
    parser.add_argument("--vars", type=int, default=3)
    parser.add_argument("--rows", type=int, default=13)
    parser.add_argument("--dtypes", nargs="+", default=["float32", "float64"])
    parser.add_argument("--settings", nargs="+", help="as scripts/device_kernels.py's")
    parser.add_argument(
        "--batch", type=int, default=1_000_000, help="problems of the launch modelled"
    )
    args = parser.parse_args()
    print(
        f"QP kernel, {args.vars} variables, {args.rows} rows, sm_{args.arch}, as launched on "
        f"{args.batch} problems"
    )
    for dtype in args.dtypes:
        for setting in parse_settings(args.settings):
            started = time.perf_counter()
            kernel = compile_kernel(
                dtype, args.vars, args.rows, setting, args.arch, batch=args.batch
            )
            r = resources(kernel.asm["cubin"])
            block, warps, maxnreg = setting
            print(
                f"{dtype} block={block} warps={warps} maxnreg={maxnreg}: {r['regs']} registers, "
                f"{r['stack']} B stack, {r['sass']} SASS instructions ({r['ldl']} local loads, "
                f"{r['stl']} stores); its longest loop {r['loop']} instructions ({r['loop_ldl']} "
                f"local loads, {r['loop_stl']} stores); compiled in "
                f"{time.perf_counter() - started:.1f} s",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
