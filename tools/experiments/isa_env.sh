# Sourced by queue_worker.sh and queue_resume.sh: every queued run and recording uses the AVX2 code paths of the
# numerical libraries, whatever the CPU offers (our choice, 2026-11-30, when the machine changed from an AMD EPYC
# without AVX-512 to an Intel Xeon with it; RESULTS' 07:50 line). The libraries pick kernels by CPU at run time, and
# other kernels round other floats: numpy's float64 exp/log (AVX512F kernels), OpenBLAS (one kernel set per core
# type), MKL's sgemm behind torch's Linear (AVX-512 kernels on Intel), torch's own vectorized ATen kernels and
# oneDNN. Capping each at AVX2 is meant to make a run compute the floats it computes on an AVX2 machine; whether it
# does is measured, not assumed (the agreement run xcpu_sr_0 against docs/results/sac_mt5_gate_avx2/sr_seed0).
# SR_NATIVE_ISA=1 leaves the libraries their own choice.
if [ "${SR_NATIVE_ISA:-0}" != 1 ]; then
  export MKL_ENABLE_INSTRUCTIONS=AVX2 ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2 OPENBLAS_CORETYPE=Haswell \
    NPY_DISABLE_CPU_FEATURES="AVX512F AVX512CD AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL"
fi
