#!/usr/bin/env bash
# `make test-matrix`: the whole suite in both environments under several OpenBLAS kernels, BLAS
# thread counts and numpy SIMD levels, as other machines would run it. Each run's first line says
# which kernel and SIMD level were really in use (test/blas_runtime.py), so a setting that did not
# take effect shows. Logs in out/test-matrix/; exits non-zero if any run failed.
set -uo pipefail
cd "$(dirname "$0")/.."
CORETYPES=${CORETYPES:-default Haswell SandyBridge Prescott Zen SkylakeX}
THREADS=${THREADS:-1 2}
ENVS=${ENVS:-.venv .venv-jazzy}
# numpy's SIMD dispatch: 'no-avx512' turns off the AVX-512 targets (names of numpy 2.x and 1.26)
NO_AVX512='X86_V4 AVX512_ICL AVX512_SPR AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL'
NO_AVX2="$NO_AVX512 X86_V3 AVX2 FMA3 AVX F16C"
mkdir -p out/test-matrix
failed=0
run() {  # env coretype threads simd
    local env=$1 core=$2 threads=$3 simd=$4 disable='' log
    case $simd in no-avx512) disable=$NO_AVX512 ;; no-avx2) disable=$NO_AVX2 ;; esac
    log=out/test-matrix/${env#.}-${core}-t${threads}-${simd}.log
    # the flags of `make test` for each environment
    local -a flags=(-q -p no:cacheprovider)
    [ "$env" = .venv-jazzy ] && flags+=(-p no:warnings)
    local -a vars=(OPENBLAS_NUM_THREADS="$threads" NPY_DISABLE_CPU_FEATURES="$disable")
    [ "$core" != default ] && vars+=(OPENBLAS_CORETYPE="$core")
    {
        env "${vars[@]}" "$env/bin/python" test/blas_runtime.py 2>/dev/null
        env "${vars[@]}" "$env/bin/python" -m pytest "${flags[@]}" 2>&1
    } > "$log"
    local rc=$? summary
    summary=$(grep -E '^[0-9]+ (passed|failed)|^FAILED' "$log" | tr '\n' ' ')
    printf '| %s | %s | %s | %s | %s | %s |\n' "$env" "$core" "$threads" "$simd" \
        "$(head -1 "$log")" "$summary"
    [ $rc -eq 0 ] || failed=1
}
echo '| env | OPENBLAS_CORETYPE | threads | numpy SIMD | in use | result |'
echo '| --- | --- | --- | --- | --- | --- |'
for env in $ENVS; do
    for core in $CORETYPES; do
        for threads in $THREADS; do run "$env" "$core" "$threads" default; done
    done
    for simd in no-avx512 no-avx2; do run "$env" default 1 "$simd"; done
done
exit $failed
