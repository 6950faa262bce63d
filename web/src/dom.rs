//! Small DOM helpers the page and the view card share (so neither imports the other for them).

use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use web_sys::{Element, Event};

pub fn document() -> web_sys::Document {
    web_sys::window()
        .and_then(|w| w.document())
        .expect("the studio runs in a page with a document")
}

/// The `silvr serve` access token in the page's query (`?token=`), for the worker's fetches of this
/// origin; the query is kept when the hash is rewritten, and share links leave the token out.
pub fn page_token() -> Option<String> {
    let search = web_sys::window()?.location().search().ok()?;
    silvr_worker::view::query_token(&search)
}

pub fn by_id(doc: &web_sys::Document, id: &str) -> Option<Element> {
    doc.get_element_by_id(id)
}

pub fn clear(el: &Element) {
    el.set_text_content(None);
}

pub fn text_el(doc: &web_sys::Document, tag: &str, class: &str, text: &str) -> Element {
    let e = doc.create_element(tag).unwrap();
    if !class.is_empty() {
        e.set_class_name(class);
    }
    e.set_text_content(Some(text));
    e
}

pub fn listen<E: JsCast + 'static>(
    target: &web_sys::EventTarget,
    name: &str,
    mut f: impl FnMut(E) + 'static,
) {
    let cb = Closure::<dyn FnMut(Event)>::new(move |ev: Event| f(ev.unchecked_into::<E>()));
    target
        .add_event_listener_with_callback(name, cb.as_ref().unchecked_ref())
        .ok();
    // Page-lifetime listeners.
    cb.forget();
}
