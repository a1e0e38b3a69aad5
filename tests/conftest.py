import pytest


@pytest.fixture(scope="module")
def torch_one_thread():
    """Tiny models run faster on one thread than oversubscribed on a busy machine; use with
    ``pytestmark = pytest.mark.usefixtures("torch_one_thread")``."""
    torch = pytest.importorskip("torch")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
