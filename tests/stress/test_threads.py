"""Same bytes whatever the thread count: a light subset rerun on a node with other cores must not differ."""

import os
import subprocess
import sys

import pytest
import torch

from diffshadow.hpc import JOB_ENVIRONMENT

pytestmark = pytest.mark.stress

# A product whose inner dimension is long enough that MKL splits its sum across threads (by default the
# last bits then depend on the thread count: 3,816 of the 4,096 outputs differed between 1 and 2 threads).
PRODUCT = """
import torch

from diffshadow.hpc import JOB_ENVIRONMENT
{first}
torch.manual_seed(0)
a, b = torch.randn(64, 32768), torch.randn(32768, 64)
torch.set_num_threads(1)
one = a @ b
torch.set_num_threads(2)
print(int((one != a @ b).sum()))
"""


def differing_outputs(job_environment: dict) -> int:
    env = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}  # the control must see MKL's default
    out = subprocess.run([sys.executable, "-c", PRODUCT.format(first="")], capture_output=True, text=True,
                         check=True, env={**env, **job_environment})
    return int(out.stdout)


@pytest.mark.skipif(not torch.backends.mkl.is_available(), reason="torch is not built with MKL")
def test_a_matrix_product_does_not_depend_on_the_thread_count():
    if differing_outputs({}) == 0:  # the control, without the workflow's job environment
        pytest.skip("this machine's MKL does not split the product across threads: nothing to show")
    assert differing_outputs(JOB_ENVIRONMENT) == 0
