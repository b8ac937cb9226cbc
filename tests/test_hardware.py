import platform

from spk2img import hardware

XEON = """processor\t: 0
model name\t: Intel(R) Xeon(R) Processor
flags\t\t: fpu avx512f avx512_bf16 amx_bf16 amx_tile amx_int8
"""
EPYC = """processor\t: 0
model name\t: AMD EPYC 7B13 64-Core Processor
flags\t\t: fpu avx2 fma
"""


def test_the_cpu_model_and_its_bf16_matrix_units_come_from_cpuinfo(tmp_path, monkeypatch):
    cpuinfo = tmp_path / "cpuinfo"
    monkeypatch.setattr(hardware, "CPUINFO", cpuinfo)
    cpuinfo.write_text(XEON)
    assert hardware.cpu_words() == "Intel(R) Xeon(R) Processor (AMX bf16)"
    cpuinfo.write_text(EPYC)
    assert hardware.cpu_words() == "AMD EPYC 7B13 64-Core Processor (no AMX)"
    cpuinfo.unlink()  # not Linux: what platform knows, and no AMX claimed
    assert hardware.cpu_model() == (platform.processor() or platform.machine())
    assert not hardware.has_amx_bf16()
