"""core.machine: the machine's description names the CPU's vector instruction set."""

from mnerf_jax.core import machine

AVX512 = "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse2 avx avx2 fma avx512f avx512bw\n"
AVX2 = "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse2 avx avx2 fma\n"


def test_the_two_cpu_kinds_of_one_model_name_are_told_apart() -> None:
    assert machine.cpu_description(AVX512) == "AMD EPYC (AVX-512)"
    assert machine.cpu_description(AVX2) == "AMD EPYC (AVX2)"


def test_a_cpu_without_either_is_named_alone_and_no_cpuinfo_falls_back_to_the_platform() -> None:
    assert machine.cpu_description("model name\t: Some CPU\nflags\t\t: fpu sse2\n") == "Some CPU"
    assert machine.cpu_description("")  # the platform's processor or machine name


def test_the_description_names_cores_python_and_jax() -> None:
    text = machine.describe()
    assert " cores, Python " in text and ", jax " in text
