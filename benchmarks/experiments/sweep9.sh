# path-source diversity at 6,000 joint steps (bunny), defaults otherwise; same evaluation pairs in all three
set -x
python benchmarks/experiments/train_sweep.py --mesh bunny --joint-steps 6000 --out $OUT/s9a --variant "def:" 2>&1 | grep "^\[\|^def"
python benchmarks/experiments/train_sweep.py --mesh bunny --joint-steps 6000 --out $OUT/s9b --data n_sources=1024 --data n_path_sources=1024 --data n_path_global=32 --variant "ps1024x32:" 2>&1 | grep "^\[\|^ps"
python benchmarks/experiments/train_sweep.py --mesh bunny --joint-steps 6000 --out $OUT/s9c --data n_sources=2048 --data n_path_sources=2048 --data n_path_global=16 --variant "ps2048x16:" 2>&1 | grep "^\[\|^ps"
