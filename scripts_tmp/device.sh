set -x
export PYTHONPATH=$PWD
nproc; python -c "import torch; print(torch.__version__, torch.cuda.is_available())"
# CUDA: the soft-metal stage on the GPU (its functions on cuda tensors; then a whole tiny recovery)
timeout 120 python scripts_tmp/cuda_check.py > $OUT/cuda.txt 2>&1 &
run() { OMP_NUM_THREADS=3 timeout 450 python -m training.evaluate --out $OUT/$1 --materials 1 --seed0 $2 --recipes $1 --size 256 --threads 3 > $OUT/$1_$2.log 2>&1; }
run rusted_metal 101 & run dusty_metal 102 & run aa_inlay 103 & run metal_inlay 101 & run tiles 102 &
wait
for f in $OUT/*/results.json; do echo $f; done
find $OUT -name "*.exr" -delete; find $OUT -name "capture.json" -delete; rm -rf $OUT/*/*_L16/img* 
cat $OUT/*.log | grep "^|" ; cat $OUT/cuda.txt
