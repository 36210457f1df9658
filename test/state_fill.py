"""A state store filled as a node leaves it, for tests that start from one: each person
written through the store's one write of a person (``StateStore.write_person``), and the
store closed, which commits them."""
from stars_ros.state import PersonUpdate, StateStore


def fill_store(folder, fingerprint: str, people: list[PersonUpdate]) -> None:
    """Fill the store in ``folder`` with ``people``, solved against checkpoint ``fingerprint``;
    OSError when the disk refuses."""
    store = StateStore(folder, 'fill_store', on_error=lambda text: None)
    store.set_fingerprint(fingerprint)
    for update in people:
        store.write_person(update)
    error, unstored = store.error, store.close()
    if error is not None or unstored:
        raise OSError(f'the state store in {folder} was not filled: {error}')
