"""The compiled CPU kernels, one file per stage or owner, each `.cpp` with its Python face beside it (as gsplat splits
its CUDA code): projection, binning (`binning.h`), compositing, the SH colours, the VM field, SSIM, depth consistency
and the PAUP scorer. `build.py` builds every `.cpp` here as one module on first use; `policy.py` is the one switch
between them and their PyTorch references (`--model.kernels compiled|torch`)."""
